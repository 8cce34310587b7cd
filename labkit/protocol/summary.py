"""A readable summary of a session against its plan (``labkit session show``)."""

from __future__ import annotations

from collections import defaultdict

from labkit.frame import exposure_label
from labkit.protocol.plan import build_plan
from labkit.session.store import MANIFEST_FILE, Session


def missing_frames(session: Session) -> tuple[int, int]:
    """(frames the session's plan has no record of, frames planned); (0, 0) for an imported
    session, which has no plan."""
    if session.info["status"] == "imported":
        return 0, 0
    keys = list(build_plan(session.rig, session.brackets).keys())
    return sum(not session.has(k) for k in keys), len(keys)


def summarise(session: Session, *, problems: dict[str, str] | None = None) -> str:
    """Status, devices, frames per scene × illumination × exposure, darks, auto choices."""
    info = session.info
    records = list(session.records.values())
    lines = [
        f"session {session.folder}",
        f"  status    {info['status']}"
        + (f" — {info['stop_reason']}" if info.get("stop_reason") else ""),
        f"  rig       {info['rig'].get('name')} (from {info.get('rig_source')}), "
        f"plan {info.get('plan_fingerprint')}",
        f"  created   {info.get('created')}, updated {info.get('updated')}",
    ]
    if "camera" in info:
        cam = info["camera"]
        lines.append(
            f"  camera    {cam.get('vendor')} {cam.get('model')} serial {cam.get('serial')}"
        )
    if "slider" in info:
        slider = info["slider"]
        lines.append(f"  slider    {slider.get('identity')} on {slider.get('port')}")
    if "imported_from" in info:
        lines.append(f"  imported  from {info['imported_from']}")
    if info["status"] != "imported":
        rig = session.rig
        plan = build_plan(rig, session.brackets)
        missing = sum(not session.has(k) for k in plan.keys())
        pending = (
            f", {plan.pending_meters} illumination(s) not yet metered"
            if (plan.pending_meters)
            else ""
        )
        lines.append(
            f"  frames    {len(records)} stored of {plan.frame_count} planned "
            f"({missing} missing{pending}), {session.stored_bytes() / 1e6:.0f} MB"
        )
    else:
        lines.append(f"  frames    {len(records)}, {session.stored_bytes() / 1e6:.0f} MB")
    if session.torn_records:
        lines.append(
            f"  manifest  {MANIFEST_FILE} ends with {session.torn_records} torn record (a crash "
            "while writing it): that frame is missing; resume the capture to re-take it"
        )
    table: dict[tuple, dict[float, int]] = defaultdict(lambda: defaultdict(int))
    for record in records:
        table[record["scene"] or "(dark)", record["illumination"]][record["exposure_s"]] += 1
    for (scene, illumination), counts in sorted(table.items()):
        text = ", ".join(f"{exposure_label(t)}×{n}" for t, n in sorted(counts.items()))
        lines.append(f"    {scene:>14} {illumination:>10}: {text}")
    for scene, by_light in info.get("brackets", {}).items():
        for illumination, choice in by_light.items():
            times = ", ".join(exposure_label(t) for t in choice["exposures_s"])
            lines.append(
                f"  auto      {scene}/{illumination}: [{times}], skipped "
                f"{len(choice.get('skipped_s', []))} ladder step(s), "
                f"{choice.get('too_dark', 0)} px too dark, {choice.get('too_bright', 0)} too bright"
                + (f", {choice['flooded']} flooded" if choice.get("flooded") else "")
                + (
                    f", {len(choice['unlinked_s'])} unlinked pair(s)"
                    if choice.get("unlinked_s")
                    else ""
                )
            )
    stats = info.get("stream_statistics")
    if stats:
        lines.append("  stream    " + ", ".join(f"{k} {v}" for k, v in stats.items()))
    for run in info.get("runs", []):
        lines.append(
            f"  run       {run.get('started')} → {run.get('stopped', '?')}: "
            f"{run.get('status', 'interrupted')}, {run.get('stored', '?')} frames"
        )
    if problems is not None:
        if problems:
            lines.append(f"  verify    {len(problems)} bad frame(s):")
            lines += [f"    {key}: {why}" for key, why in sorted(problems.items())[:20]]
        else:
            lines.append(f"  verify    all {len(records)} frames match their sha256")
    return "\n".join(lines)
