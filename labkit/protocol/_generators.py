"""Running a generator of requests to its end: the one loop that the auto-bracketing
sequences and the protocol's steps are driven by, directly (:func:`drive`) or from inside
another generator such as a Bluesky plan (:func:`drive_within`)."""

from __future__ import annotations

from collections.abc import Callable, Generator
from typing import Any, TypeVar

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


def drive_within(
    steps: Generator[_Request, _Answer | None, _Result],
    answer: Callable[[_Request], Generator[Any, Any, _Answer | None]],
) -> Generator[Any, Any, _Result]:
    """:func:`drive` where each answer is itself a generator (a Bluesky plan carrying the
    request out): what it yields is passed on, what it returns is sent to `steps`."""
    reply: _Answer | None = None
    try:
        while True:
            reply = yield from answer(steps.send(reply))
    except StopIteration as finished:
        return finished.value
