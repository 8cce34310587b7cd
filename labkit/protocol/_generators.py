"""Running a generator of requests to its end: the one loop that the auto-bracketing
sequences and the protocol's steps are driven by."""

from __future__ import annotations

from collections.abc import Callable, Generator
from typing import TypeVar

_Request = TypeVar("_Request")
_Answer = TypeVar("_Answer")
_Result = TypeVar("_Result")


def drive(
    steps: Generator[_Request, _Answer, _Result], answer: Callable[[_Request], _Answer]
) -> _Result:
    """Send `steps` ``answer(request)`` for every request it yields, until it returns;
    return what it returns."""
    try:
        request = next(steps)
        while True:
            request = steps.send(answer(request))
    except StopIteration as finished:
        return finished.value
