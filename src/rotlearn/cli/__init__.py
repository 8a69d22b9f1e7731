"""Floor 5: command-line entry points (Hydra mains and argparse), Hydra callbacks."""

import atexit
import contextlib
import gc
from collections.abc import Iterator

from rotlearn.extras import require

require("train", "rotlearn's command line")

from rotlearn.config import resolvers  # noqa: F401  (registers the config resolvers)


@contextlib.contextmanager
def refusals_exit_at_once() -> Iterator[None]:
    """A refusal (SystemExit) inside the block ends the process without the garbage collector's
    last walk over every object at exit (`gc.freeze` at exit: torch's objects make that walk
    0.3-0.5 s on 2 cores, a fifth of the time a mistake takes to be answered). Nothing was
    written, so no finaliser has anything to finish; in a process that goes on (a test), only
    its own exit is affected."""
    try:
        yield
    except SystemExit:
        atexit.register(gc.freeze)
        raise
