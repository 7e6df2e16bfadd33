"""One error type for bad input: it renders as a single line naming where the problem is."""

from __future__ import annotations


def clip(text: str, limit: int = 160) -> str:
    """`text` on one line, at most about `limit` characters: a longer one is cut at the last
    space before the limit and ends in "...", never in the middle of a word (a library's
    message quoted in ours: "Either the file is corrupted or th" read as a second fault)."""
    text = " ".join(str(text).split())
    if len(text) <= limit:
        return text
    cut = text.rfind(" ", 0, limit)
    return text[:cut if cut > limit // 2 else limit].rstrip(" ,;:(") + " ..."


class SefaInputError(Exception):
    """Bad input data or configuration.

    Rendered as ``<file>: <topic or key>: <what> (at <where>)`` so that a user sees in one line
    which file, which stream and which time or index is wrong.
    """

    def __init__(self, what: str, *, file: str | None = None, key: str | None = None,
                 where: str | None = None):
        self.what, self.file, self.key, self.where = what, file, key, where
        super().__init__(self.line())

    def line(self) -> str:
        parts = [p for p in (self.file, self.key) if p]
        text = ": ".join(parts + [self.what])
        if self.where:
            text += f" (at {self.where})"
        return text

    def with_file(self, file: str) -> "SefaInputError":
        """The same error with the file filled in when the raiser did not know it."""
        if self.file is None:
            return SefaInputError(self.what, file=file, key=self.key, where=self.where)
        return self


class ConfigError(SefaInputError):
    """An unknown or ill-typed configuration key."""


class NonFiniteError(SefaInputError):
    """A value that must be finite is not (a loss, weights, actions, a metric): nothing built
    from it is published."""
