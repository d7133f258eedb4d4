"""Data modules and the shared batch format."""

from dider.data.batch import Batch, Normalizer

__all__ = ["Batch", "Normalizer"]
