"""The app's Hydra configs. Importing this package registers the resolvers they use, so they compose wherever
Hydra is initialised with it (``initialize_config_module("dider.conf")``, ``pkg://dider.conf``)."""

from dider.training.resolvers import register_resolvers

register_resolvers()
