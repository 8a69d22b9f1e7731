"""Floor 4: command-line entry points (Hydra mains), config schemas, resolvers, Hydra callbacks."""

from rotlearn.cli import resolvers  # noqa: F401  (registers the config resolvers)
