"""Errors raised by the client."""

from __future__ import annotations

from typing import Optional


class RigdError(Exception):
    """A non-2xx answer from rigd.

    ``status`` is the HTTP status; ``error`` and ``detail`` come from rigd's
    error body ``{"error": CODE, "detail": TEXT}`` (``error`` is None when the
    answer had no such body, e.g. a 431; ``detail`` then holds the start of
    whatever the body was).
    """

    def __init__(
        self,
        status: int,
        error: Optional[str],
        detail: str,
        *,
        method: str = "",
        url: str = "",
        hint: str = "",
    ) -> None:
        self.status = status
        self.error = error
        self.detail = detail
        self.method = method
        self.url = url
        self.hint = hint
        super().__init__(str(self))

    def __str__(self) -> str:
        where = f"{self.method} {self.url}: " if self.method else ""
        code = f" {self.error}" if self.error else ""
        hint = f" ({self.hint})" if self.hint else ""
        return f"{where}{self.status}{code}: {self.detail}{hint}"


class RigdTimeout(TimeoutError):
    """A client-side wait (``wait``, ``wait_process``) ran out of time.

    ``last`` holds the last view seen (a run or a process job), if any.
    """

    def __init__(self, message: str, last: Optional[dict] = None) -> None:
        super().__init__(message)
        self.last = last
