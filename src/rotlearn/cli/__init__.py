"""Floor 5: command-line entry points (Hydra mains and argparse), resolvers, Hydra callbacks."""

from rotlearn.extras import require

require("train", "rotlearn's command line")

from rotlearn.cli import resolvers  # noqa: F401  (registers the config resolvers)
