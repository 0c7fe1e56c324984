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


def headless() -> bool:
    """Whether dialogs raise :class:`GuiError` instead of showing (see :func:`set_headless`)."""
    return _headless


def close_modal_dialogs() -> int:
    """Reject every open modal dialog (message box, question, file dialog), innermost first,
    as if the operator had pressed Esc; returns how many.

    Each runs its own event loop, in which the window's close and the application's quit
    wait: a signal that closes the window must end them first (SIGTERM over a "Cannot open
    session" box left the process to SIGKILL). A rejected question answers no."""
    app = QtWidgets.QApplication.instance()
    if app is None:
        return 0
    closed: list[QtWidgets.QWidget] = []
    while (widget := QtWidgets.QApplication.activeModalWidget()) is not None:
        if widget in closed:  # would not go (a dialog that refuses to close): hide it
            widget.hide()
            if QtWidgets.QApplication.activeModalWidget() is widget:
                break
            continue
        closed.append(widget)
        if isinstance(widget, QtWidgets.QDialog):
            widget.reject()  # ends its exec(); a message box without Esc button too
        else:
            widget.close()
    return len(closed)


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
