"""Zarr episode stores, padded windows, normalizers and DataModules (Diffusion Policy's data path)."""

from datasets.errors import DataError
from datasets.store import EpisodeStore

__all__ = ["DataError", "EpisodeStore"]
