"""Command families of the ``pelvislab`` CLI; each module exposes ``register(subparsers)``.

A handler takes the parsed ``argparse.Namespace`` and returns an exit code (or None for 0).
Heavy imports (numpy, h5py, Qt) happen inside handlers so that ``--help`` stays fast.
"""

from pelvislab.app.commands import (
    bench,
    demo,
    ema,
    gap,
    gui,
    identify,
    model_cmd,
    protocol,
    run,
    session,
    uff,
)

COMMAND_MODULES = (run, protocol, bench, session, gui, model_cmd, identify, ema, gap, uff,
                   demo)
