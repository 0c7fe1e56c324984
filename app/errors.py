"""Exceptions the command line turns into exit codes and one-line messages."""


class NotImplementedCommand(Exception):
    """A registered subcommand whose feature is not built yet (exit code 2)."""

    def __init__(self, command: str) -> None:
        super().__init__(f"{command}: not implemented yet")
