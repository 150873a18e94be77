"""Pinhole camera in the OpenCV convention (+x right, +y down, +z forward)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, TypeVar

import torch

T = TypeVar("T")


@dataclass
class Camera:
    """A pinhole camera.

    K: [3, 3] pixel intrinsics (fx, fy, cx, cy; the pixel (i, j) has its centre at (i+0.5, j+0.5)).
    viewmat: [4, 4] world-to-camera transform.
    """

    K: torch.Tensor
    viewmat: torch.Tensor
    width: int
    height: int

    def __post_init__(self) -> None:
        # tensors stay where they are (as_tensor would move them to torch's default device)
        if not isinstance(self.K, torch.Tensor):
            self.K = torch.as_tensor(self.K)
        if not isinstance(self.viewmat, torch.Tensor):
            self.viewmat = torch.as_tensor(self.viewmat)
        if self.K.shape != (3, 3):
            raise ValueError(f"Camera.K must be [3,3], got {tuple(self.K.shape)}")
        if self.viewmat.shape != (4, 4):
            raise ValueError(f"Camera.viewmat must be [4,4] world-to-camera, got {tuple(self.viewmat.shape)}")
        self.width, self.height = int(self.width), int(self.height)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"Camera size must be positive, got {self.width}x{self.height}")

    def memo(self, key: tuple, make: Callable[[], T]) -> T:
        """``make()``, kept on this camera under ``key`` until the camera changes: another K or
        viewmat tensor, a write into one (the tensor's version counter), another size. For what
        every render derives from the camera alone (the packed view, on the host and on a device):
        computing it cost a render 0.3 ms of small host operations. Not kept where K or viewmat
        needs a gradient (the derived tensor would carry a stale graph)."""
        K, V = self.K, self.viewmat
        if K.requires_grad or V.requires_grad:
            return make()
        stamp = (K._version, V._version, self.width, self.height)
        memo = self.__dict__.setdefault("_memo", {})
        hit = memo.get(key)
        if hit is not None and hit[0] is K and hit[1] is V and hit[2] == stamp:
            return hit[3]
        value = make()
        memo[key] = (K, V, stamp, value)
        return value

    def __getstate__(self) -> dict:
        # the memo holds device tensors: never pickled or copied with the camera
        return {k: v for k, v in self.__dict__.items() if k != "_memo"}

    @property
    def camtoworld(self) -> torch.Tensor:
        return torch.linalg.inv(self.viewmat)

    @property
    def center(self) -> torch.Tensor:
        """Camera centre in world coordinates."""
        return self.camtoworld[:3, 3]

    def to(self, device=None, dtype=None) -> "Camera":
        return Camera(self.K.to(device=device, dtype=dtype), self.viewmat.to(device=device, dtype=dtype),
                      self.width, self.height)

    def scaled(self, factor: float) -> "Camera":
        """The same camera with the image resized by ``factor`` (pixel-centre convention kept)."""
        K = self.K.clone()
        w, h = round(self.width * factor), round(self.height * factor)
        # Per-axis factors of the rounded size, so the image edges stay on the same rays.
        K[0] = self.K[0] * (w / self.width)
        K[1] = self.K[1] * (h / self.height)
        return Camera(K, self.viewmat.clone(), w, h)

    @staticmethod
    def look_at(eye, target, up, fx: float, fy: float, width: int, height: int,
                cx: float | None = None, cy: float | None = None) -> "Camera":
        """Camera at ``eye`` looking at ``target``; ``up`` is the world up (image -y)."""
        eye, target, up = (torch.as_tensor(v, dtype=torch.float64) for v in (eye, target, up))
        z = target - eye
        z = z / z.norm()
        x = torch.linalg.cross(z, up)
        x = x / x.norm()
        y = torch.linalg.cross(z, x)
        R = torch.stack([x, y, z])  # rows: camera axes in world coordinates
        viewmat = torch.eye(4, dtype=torch.float64)
        viewmat[:3, :3] = R
        viewmat[:3, 3] = -R @ eye
        K = torch.tensor([[fx, 0.0, width / 2 if cx is None else cx],
                          [0.0, fy, height / 2 if cy is None else cy],
                          [0.0, 0.0, 1.0]], dtype=torch.float64)
        return Camera(K.float(), viewmat.float(), width, height)
