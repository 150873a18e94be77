"""Scenes and their loaders."""

from smgs.data.scene import Scene, View, camera_extent

__all__ = ["Scene", "View", "camera_extent"]
