"""A Bluesky run of the ophyd-async devices, written into a Tiled server on 127.0.0.1 by
TiledWriter (bluesky-tiled-plugins): its frames are reachable from the run and read back
bit for bit equal to the session's TIFFs, with their metadata beside them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from bluesky import RunEngine

from labkit.bluesky import PRIMARY, capture_protocol, open_session_devices
from labkit.io import read_raw_tiff
from labkit.rig import load_rig
from labkit.session import Session

pytest.importorskip("tiled", reason="labkit[tiled] is not installed")
pytest.importorskip("bluesky_tiled_plugins", reason="labkit[tiled] is not installed")


def test_a_runs_frames_are_reachable_through_tiled_writer(
    quick_rig_file: Path, tmp_path: Path
) -> None:
    from bluesky_tiled_plugins import TiledWriter
    from tiled.client import from_uri
    from tiled.server import SimpleTiledServer

    folder = tmp_path / "session"
    server = SimpleTiledServer(tmp_path / "tiled", readable_storage=[tmp_path])
    try:
        assert server.uri.startswith("http://127.0.0.1:")
        client = from_uri(server.uri)
        engine = RunEngine({})
        engine.subscribe(TiledWriter(client, batch_size=1))
        with open_session_devices(load_rig(quick_rig_file), folder) as d:
            (uid,) = engine(capture_protocol(d.detector, d.slider, d.scene, d.cover))
        primary = client[uid][PRIMARY]
        frames = primary["camera"].read()
        table = primary.read()
    finally:
        server.close()
    session = Session.open(folder)
    keys = [str(key) for key in table["camera-key"].values]
    assert frames.dtype == np.uint16 and frames.shape == (len(session.records), 1, 64, 96)
    assert sorted(keys) == sorted(session.records)
    for index, key in enumerate(keys):
        record = session.records[key]
        image, _ = read_raw_tiff(folder / record["file"])
        np.testing.assert_array_equal(frames[index, 0], image, err_msg=key)
        assert int(table["camera-frame_id"].values[index]) == record["frame_id"]
        exposure_s = float(table["camera-exposure_s"].values[index])
        assert exposure_s == pytest.approx(record["exposure_s"], rel=1e-9)  # check_frame's
