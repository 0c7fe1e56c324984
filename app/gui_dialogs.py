"""Dialogs of the operator GUI, and what replaces them when nobody can answer.

With ``pelvislab gui --screenshot`` the window is rendered offscreen and no one can click a
modal message box: the process hung (a bad replay file, an unusable protocol). There,
:func:`alert` raises :class:`GuiError` instead, which the command prints as its one-line
reason (exit 1).
"""

from __future__ import annotations

from PySide6 import QtWidgets


class GuiError(RuntimeError):
    """What a dialog would have said, raised where no one can answer a dialog."""


_headless = False


def set_headless(on: bool) -> None:
    """Raise instead of showing modal dialogs (offscreen rendering)."""
    global _headless
    _headless = bool(on)


def alert(parent: QtWidgets.QWidget | None, title: str, text: str,
          critical: bool = True) -> None:
    """A modal warning/critical message box, or :class:`GuiError` when headless."""
    text = " ".join(str(text).split())
    if _headless:
        raise GuiError(f"{title}: {text}")
    if critical:
        QtWidgets.QMessageBox.critical(parent, title, text)
    else:
        QtWidgets.QMessageBox.warning(parent, title, text)


def ask(parent: QtWidgets.QWidget | None, title: str, text: str) -> bool:
    """A yes/no question; where nobody can answer (headless) the answer is no."""
    if _headless:
        return False
    answer = QtWidgets.QMessageBox.question(parent, title, text)
    return answer == QtWidgets.QMessageBox.StandardButton.Yes
