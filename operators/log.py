"""VP-FFD's console lines. Every module logs through its own logger (`logging.getLogger(__name__)`)
below the extension's package; Blender configures no logging of its own, so registering the
extension gives that package one handler that prints to standard output as `VP-FFD: <message>`,
the lines a farm's log is searched for (README, *Checking a worker*)."""
import logging
import sys

PACKAGE = __package__.rsplit(".", 1)[0]     # the extension's package, e.g. bl_ext.user_default.vpffd
PREFIX = "VP-FFD: "

_handler = None


class _Stdout(logging.StreamHandler):
    """A stream handler on whatever `sys.stdout` is when a line is written (Blender and test
    runners replace it)."""

    def __init__(self):
        super().__init__(sys.stdout)

    def emit(self, record):
        self.stream = sys.stdout
        super().emit(record)


def install():
    """Print the extension's log records (INFO and above) as `VP-FFD: ...` lines."""
    global _handler
    logger = logging.getLogger(PACKAGE)
    if _handler is None:
        _handler = _Stdout()
        _handler.setFormatter(logging.Formatter(PREFIX + "%(message)s"))
    if _handler not in logger.handlers:
        logger.addHandler(_handler)
    logger.setLevel(logging.INFO)
    logger.propagate = False


def uninstall():
    if _handler is not None:
        logging.getLogger(PACKAGE).removeHandler(_handler)
