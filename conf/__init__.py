"""The app's Hydra configs. Importing this package registers the resolvers they use and the plugins' schemas
(:mod:`dider.training.schemas`), so they compose wherever Hydra is initialised with it
(``initialize_config_module("dider.conf")``, ``pkg://dider.conf``)."""

from dider.training.resolvers import register_resolvers
from dider.training.schemas import register_schemas

register_resolvers()
register_schemas()
