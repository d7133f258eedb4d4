"""dider: relational inference of dynamically evolving interactions (DIDER, DNRI, NRI)."""

__version__ = "0.1.0"
