"""The errors of the Mitsuba bridge: what cannot be translated or rendered, said in one line.

* :class:`TranslationError`: one USD value that cannot be translated, built from the prim,
  the attribute and the reason (``/World/Cam.focalLength: must be > 0, got 0``); a
  :class:`usdfiber.errors.PrimError` (the core's one prim-error type) without a file.
* :class:`TranslateError`: a prim (or a stage) that cannot be rendered, with a message that
  already names the prim and the attribute; :func:`~usdfiber.translators.mitsuba.scene.translate_stage`
  raises it for every problem, translation errors of the modules below included.
* :class:`RenderRefused`: a render that will not run (a stage with ``usdfiber check`` errors,
  an unusable device, an image that would not be finite); ``usdfiber render`` prints it and
  exits with status 1.
"""
from __future__ import annotations

from pxr import Sdf

from usdfiber.errors import PrimError

__all__ = ["RenderRefused", "TranslateError", "TranslationError"]


class TranslationError(PrimError):
    """A USD value that cannot be translated; the message (one line) names the prim and attribute."""

    def __init__(self, prim: str | Sdf.Path, attribute: str | None, reason: str) -> None:
        super().__init__(None, str(prim), attribute, reason)

    def __reduce__(self) -> tuple:
        return (type(self), (self.prim, self.attribute, self.expected))


class TranslateError(RuntimeError):
    """A prim that cannot be rendered; the message names the prim and the attribute.

    Raised with a finished message (often a core error's text, which names the file too), so
    it is not a :class:`~usdfiber.errors.PrimError`, whose fields it would have to parse back."""


class RenderRefused(RuntimeError):
    """The stage cannot be rendered; the message says why (problems as `usdfiber check`)."""
