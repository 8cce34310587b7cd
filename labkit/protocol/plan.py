"""The capture plan of thesis Algorithm 10: a list of steps, printed, validated, then run.

For every scene, for the open position and each filter: move the slider, then grab
`replicates` frames at each exposure time; at the end, cover the light and grab dark
frames for every exposure time used, as many as the most replicates used at that time
(shared by all scenes). Exposure lists marked ``auto`` in the rig are chosen at run time
from a metering frame (:mod:`labkit.protocol.bracketing`); until then the plan holds a
:class:`Meter` step in their place, and the engine rebuilds the plan once it knows them.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from labkit.devices.camera import Camera
from labkit.devices.slider import FilterSlider
from labkit.errors import ConfigError
from labkit.frame import DARK, FrameKey, exposure_label
from labkit.rig import Rig


@dataclass(frozen=True)
class SetScene:
    """Put a scene in front of the camera (an operator action on a real rig)."""

    scene: str

    def describe(self) -> str:
        return f"set scene {self.scene!r}"


@dataclass(frozen=True)
class MoveFilter:
    """Move the slider to the slot holding an illumination's filter."""

    slot: int
    illumination: str

    def describe(self) -> str:
        return f"move slider to slot {self.slot} ({self.illumination})"


@dataclass(frozen=True)
class CoverLight:
    """Cover the light source (before dark frames)."""

    def describe(self) -> str:
        return "cover the light (dark frames)"


@dataclass(frozen=True)
class UncoverLight:
    """Uncover the light source."""

    def describe(self) -> str:
        return "uncover the light"


@dataclass(frozen=True)
class Meter:
    """Take metering frames and choose the exposure times of one illumination."""

    scene: str
    illumination: str
    replicates: int

    def describe(self) -> str:
        return (
            f"meter {self.scene}/{self.illumination} and choose its exposure times "
            f"(× {self.replicates} replicates each)"
        )


@dataclass(frozen=True)
class Capture:
    """Grab `replicates` frames at one exposure time."""

    scene: str | None
    illumination: str
    exposure_s: float
    replicates: int

    def keys(self) -> list[FrameKey]:
        """The frames this step stores."""
        return [
            FrameKey(self.scene, self.illumination, self.exposure_s, r)
            for r in range(self.replicates)
        ]

    def describe(self) -> str:
        what = "dark" if self.scene is None else f"{self.scene}/{self.illumination}"
        return f"grab {what} at {exposure_label(self.exposure_s)} × {self.replicates}"


Step = SetScene | MoveFilter | CoverLight | UncoverLight | Meter | Capture


@dataclass(frozen=True)
class Plan:
    """An ordered list of steps and what it will store."""

    steps: tuple[Step, ...]
    slots: Mapping[str, int] = field(default_factory=dict)

    def __iter__(self) -> Iterator[Step]:
        return iter(self.steps)

    def captures(self) -> list[Capture]:
        """The capture steps, in order."""
        return [step for step in self.steps if isinstance(step, Capture)]

    def keys(self) -> list[FrameKey]:
        """Every frame the plan stores (so far as exposures are known)."""
        return [key for step in self.captures() for key in step.keys()]

    @property
    def frame_count(self) -> int:
        """Frames the plan stores (so far as exposures are known)."""
        return sum(step.replicates for step in self.captures())

    @property
    def pending_meters(self) -> int:
        """Metering steps whose exposure times are still unknown."""
        return sum(isinstance(step, Meter) for step in self.steps)

    def exposures_used(self) -> list[float]:
        """Distinct exposure times of the lit captures, s, ascending."""
        return sorted({c.exposure_s for c in self.captures() if c.scene is not None})

    def describe(self) -> str:
        """A numbered, human-readable listing (``labkit capture --dry-run``)."""
        lines = [f"{i + 1:4d}. {step.describe()}" for i, step in enumerate(self.steps)]
        total = f"{self.frame_count} frames"
        if self.pending_meters:
            total += f" + the auto-bracketed frames of {self.pending_meters} metered step(s)"
        return "\n".join([*lines, f"total: {total}"])


def update_desired_state(desired: dict[str, Any], step: Step) -> bool:
    """Record a set-up step's effect in `desired` (``scene``, ``slot``, ``covered``), the
    state the hardware must be in before the next capture; returns whether `step` was a
    set-up step. The engine (and the Bluesky plan) apply it only before frames are taken,
    so a resumed run goes straight to its first missing frame."""
    if isinstance(step, SetScene):
        desired["scene"] = step.scene
    elif isinstance(step, MoveFilter):
        desired["slot"] = step.slot
    elif isinstance(step, CoverLight | UncoverLight):
        desired["covered"] = isinstance(step, CoverLight)
    else:
        return False
    return True


def pending_changes(desired: dict[str, Any], state: dict[str, Any]) -> list[tuple[str, Any]]:
    """What must change for the hardware `state` to match `desired`, in the order to do it:
    ``("covered", bool)`` (the light is uncovered unless a step covered it), then
    ``("scene", name)``, then ``("slot", number)``. Neither mapping is changed: the caller
    records each change in `state` once it is done."""
    changes: list[tuple[str, Any]] = []
    covered = desired.get("covered", False)
    if state.get("covered") != covered:
        changes.append(("covered", covered))
    for key in ("scene", "slot"):
        if key in desired and state.get(key) != desired[key]:
            changes.append((key, desired[key]))
    return changes


def build_plan(rig: Rig, brackets: Mapping[tuple[str, str], Sequence[float]] | None = None) -> Plan:
    """The plan of a rig (thesis Algorithm 10).

    Parameters
    ----------
    rig : Rig
        Scenes, illuminations, exposure times, replicates and dark-frame switch.
    brackets : mapping (scene, illumination) → exposure times (s), optional
        Exposure times already chosen for ``auto`` illuminations; the others get a
        :class:`Meter` step.
    """
    brackets = brackets or {}
    slots = {p.name: slot for slot, p in rig.slider.positions.items()}
    steps: list[Step] = []
    dark_replicates: dict[float, int] = {}
    for scene in rig.plan.scenes:
        steps += [SetScene(scene), UncoverLight()]
        for illumination in rig.illuminations():
            replicates = rig.replicates_for(illumination)
            steps.append(MoveFilter(slots[illumination], illumination))
            times = rig.exposures_for(illumination)
            if times == "auto":
                if (scene, illumination) not in brackets:
                    steps.append(Meter(scene, illumination, replicates))
                    continue
                times = list(brackets[scene, illumination])
            for exposure_s in times:
                steps.append(Capture(scene, illumination, float(exposure_s), replicates))
                previous = dark_replicates.get(float(exposure_s), 0)
                dark_replicates[float(exposure_s)] = max(previous, replicates)
    if rig.plan.dark_frames and dark_replicates:
        steps.append(CoverLight())
        steps += [Capture(None, DARK, t, n) for t, n in sorted(dark_replicates.items())]
    return Plan(tuple(steps), slots)


def validate_plan(plan: Plan, camera: Camera, slider: FilterSlider | None = None) -> None:
    """Check a plan against the hardware before anything moves.

    Raises
    ------
    ConfigError
        An exposure time outside the camera's bounds, or a slot the slider does not have.
    DeviceError
        The camera cannot control its exposure time at all (from ``exposure_bounds``).
    """
    if any(isinstance(s, Capture | Meter) for s in plan.steps):
        bounds = camera.exposure_bounds()  # raises for cameras without exposure control
        bad = sorted({c.exposure_s for c in plan.captures() if not bounds.contains(c.exposure_s)})
        if bad:
            where = sorted({c.illumination for c in plan.captures() if c.exposure_s in bad})
            raise ConfigError(
                f"exposure time(s) {', '.join(f'{t:g} s' for t in bad)} (for {', '.join(where)}) "
                f"are outside the camera's range [{bounds.minimum:g}, {bounds.maximum:g}] s; "
                "change plan.exposures_s in the rig file"
            )
    if slider is not None:
        count = slider.slot_count
        bad_slots = sorted(
            {s.slot for s in plan.steps if isinstance(s, MoveFilter)} - set(range(1, count + 1))
        )
        if bad_slots:
            raise ConfigError(
                f"slider positions {bad_slots} do not exist on the slider at {slider.port} "
                f"({count} slots, numbered 1–{count}); fix slider.positions in the rig file"
            )
