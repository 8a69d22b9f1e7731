"""Floor 4: command-line entry points (Hydra mains), config schemas, resolvers, Hydra callbacks."""

from rotlearn.extras import require

require("train", "rotlearn's command line")

from rotlearn.cli import resolvers  # noqa: F401  (registers the config resolvers)
