"""Rendering: one scene description (scene.py, camera.py), two backends (raycast.py: Open3D; blender.py: Cycles)."""
