"""Geometry backends behind one adapter each (``open3d_adapter``: the only module that imports Open3D)."""
