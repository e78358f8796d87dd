"""Zarr episode stores, padded windows, normalizers and DataModules (Diffusion Policy's data path)."""

from gpc.datasets.errors import DataError
from gpc.datasets.store import EpisodeStore

__all__ = ["DataError", "EpisodeStore"]
