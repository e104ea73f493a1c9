"""Configuration: Hydra composition of ``conf/`` and access to the composed ``params.yaml``."""
