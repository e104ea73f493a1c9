"""File formats and atomic writes: the only package that touches the file system layout of outputs."""
