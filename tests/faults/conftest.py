"""Fixtures and the verdict table of the fault suite (see ``_faults``)."""

from _faults import (  # noqa: F401 - fixtures and a hook, registered by name
    pipeline,
    probe,
    pytest_terminal_summary,
    small_disk,
    workspace,
)
