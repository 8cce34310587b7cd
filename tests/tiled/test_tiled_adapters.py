"""labkit's files served by Tiled from a server on 127.0.0.1: what the Tiled client reads
back equals what labkit's own readers read from the files, bit for bit — a session's
frames with their records, an HDR raw EXR, a spectral EXR with its wavelengths in nm —
and a dispersion model's facts arrive as metadata; files labkit does not know are left
out, and the server refuses clients without its API key."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from _helpers import QUICK_PLAN, lens_model_file, write_rig

from labkit.cli import main
from labkit.io import (
    SpectralImage,
    read_raw_exr,
    read_raw_tiff,
    read_spectral_exr,
    write_spectral_exr,
)
from labkit.session import Session

pytest.importorskip("tiled", reason="labkit[tiled] is not installed")

from tiled.client import from_uri

from labkit.tiled import (
    DISPERSION_MODEL,
    RAW_EXR,
    SESSION,
    SPECTRAL_EXR,
    detect_mimetype,
)
from labkit.tiled.server import serving

WAVELENGTHS_NM = np.array([452.25, 500.0, 550.125, 601.5, 650.0])


@pytest.fixture(scope="module")
def lab_folder(tmp_path_factory: pytest.TempPathFactory, sim_rig_path: Path) -> Path:
    """A lab's data folder: a session, its HDR merge, a spectral image, a lens model and
    a file labkit does not know."""
    folder = tmp_path_factory.mktemp("lab")
    rig = write_rig(tmp_path_factory.mktemp("rig"), sim_rig_path, **QUICK_PLAN)
    assert main(["capture", str(rig), "--session", str(folder / "sessions" / "day1"),
                 "--fast", "--yes", "--no-progress"]) == 0  # fmt: skip
    assert main(["hdr", str(folder / "sessions" / "day1"), "--out", str(folder / "hdr"),
                 "--no-preview"]) == 0  # fmt: skip
    cube = np.random.default_rng(3).random((12, 16, WAVELENGTHS_NM.size)).astype(np.float32)
    (folder / "recon").mkdir()
    write_spectral_exr(folder / "recon" / "spectral.exr", SpectralImage(cube, WAVELENGTHS_NM))
    lens_model_file(folder / "lens.yaml", (64, 96))
    (folder / "notes.txt").write_text("not a labkit file")
    return folder


def test_labkits_mimetypes_are_told_from_the_files(lab_folder: Path) -> None:
    assert detect_mimetype(lab_folder / "sessions" / "day1") == SESSION
    assert detect_mimetype(lab_folder / "hdr" / "disks" / "450.exr") == RAW_EXR
    assert detect_mimetype(lab_folder / "recon" / "spectral.exr") == SPECTRAL_EXR
    assert detect_mimetype(lab_folder / "lens.yaml") == DISPERSION_MODEL
    assert detect_mimetype(lab_folder / "hdr" / "hdr.yaml", "application/x-yaml") == (
        "application/x-yaml"
    )
    assert detect_mimetype(lab_folder / "notes.txt", "text/plain") == "text/plain"
    assert detect_mimetype(lab_folder / "sessions") is None


def test_a_tiled_server_serves_labkits_files_bit_for_bit(lab_folder: Path) -> None:
    with serving(lab_folder) as (uri, api_key):
        assert uri.startswith("http://127.0.0.1:")
        client = from_uri(uri, api_key=api_key)
        assert sorted(client) == ["hdr", "lens", "recon", "sessions"]  # no notes.txt

        # the session: its session.yaml, and every frame with its record
        served = client["sessions"]["day1"]
        session = Session.open(lab_folder / "sessions" / "day1")
        assert served.metadata["plan_fingerprint"] == session.info["plan_fingerprint"]
        assert served.metadata["status"] == "complete"
        frames = served["frames"]
        seen = 0
        for record in session.records.values():
            node = frames
            for part in Path(record["file"]).with_suffix("").parts[1:]:
                node = node[part]
            pixels = node.read()
            expected, _ = read_raw_tiff(session.folder / record["file"])
            assert pixels.dtype == np.uint16
            np.testing.assert_array_equal(pixels, expected, err_msg=record["key"])
            assert node.metadata["sha256"] == record["sha256"]
            seen += 1
        assert seen == len(session.records) == 38

        # an HDR raw EXR: raw and variance, with its attributes
        hdr = client["hdr"]["disks"]["450"]
        dataset = hdr.read()
        image = read_raw_exr(lab_folder / "hdr" / "disks" / "450.exr")
        assert dataset["raw"].dtype == np.float32
        np.testing.assert_array_equal(dataset["raw"].values, image.raw)
        if image.variance is None:
            assert list(dataset.data_vars) == ["raw"]
        else:
            np.testing.assert_array_equal(dataset["variance"].values, image.variance)
        assert dataset.attrs["cfa"] == image.cfa
        assert dataset.attrs["exposure_s"] == image.exposure_s
        assert dataset.attrs["wavelength_nm"] == image.wavelength_nm == 450.0

        # a spectral EXR, with its wavelength axis in nm
        spectral = client["recon"]["spectral"].read()
        expected = read_spectral_exr(lab_folder / "recon" / "spectral.exr")
        assert spectral["spectral"].dims == ("y", "x", "wavelength")
        np.testing.assert_array_equal(spectral["spectral"].values, expected.cube)
        np.testing.assert_array_equal(spectral["wavelength"].values, WAVELENGTHS_NM)
        assert spectral.attrs["wavelength_units"] == "nm"
        assert spectral.attrs["wavelengths_nm"] == WAVELENGTHS_NM.tolist()

        # the dispersion model's facts, its domain among them
        model = yaml.safe_load((lab_folder / "lens.yaml").read_text())
        metadata = client["lens"].metadata
        assert metadata["kind"] == "labkit.dispersion_model"
        assert metadata["region"]["wavelength_nm"] == model["region"]["wavelength_nm"]
        assert metadata["fields"].keys() == model["fields"].keys()

        # the key is required
        with pytest.raises(Exception, match="requires API key authentication"):
            from_uri(uri, api_key="not-the-key")["sessions"]


def test_labkit_serve_refuses_what_it_cannot_serve(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["serve", str(tmp_path / "absent")]) == 2
    assert "is not a folder" in capsys.readouterr().err
    assert main(["serve", str(tmp_path), "--port", "70000"]) == 2
    assert "not a port number" in capsys.readouterr().err


def test_labkits_adapters_serve_from_a_tiled_catalog(lab_folder: Path, tmp_path: Path) -> None:
    """Registered in a Tiled catalog with labkit's mimetype hook and adapters (what ``tiled
    serve directory --mimetype-hook labkit.tiled:detect_mimetype --adapter …`` does), the
    files are served as by ``labkit serve``."""
    import asyncio

    import uvicorn
    from tiled.catalog import from_uri as catalog_from_uri
    from tiled.client.register import register
    from tiled.config import Authentication
    from tiled.server.app import build_app
    from tiled.server.simple import ThreadedServer

    from labkit.tiled import ADAPTERS_BY_MIMETYPE

    catalog = catalog_from_uri(
        tmp_path / "catalog.db",
        writable_storage=[tmp_path / "data"],
        readable_storage=[lab_folder],
        init_if_not_exists=True,
        adapters_by_mimetype=ADAPTERS_BY_MIMETYPE,
    )
    app = build_app(catalog, authentication=Authentication(single_user_api_key="key"))
    config = uvicorn.Config(app, host="127.0.0.1", port=0, log_level="warning")
    with ThreadedServer(config).run_in_thread() as uri:
        client = from_uri(uri, api_key="key")
        asyncio.run(
            register(
                client,
                lab_folder,
                mimetype_detection_hook="labkit.tiled:detect_mimetype",
                adapters_by_mimetype=dict(ADAPTERS_BY_MIMETYPE),
            )
        )
        assert sorted(client) == ["hdr", "lens", "recon", "sessions"]
        session = Session.open(lab_folder / "sessions" / "day1")
        record = session.records["disks/450/100ms/r001"]
        served = client["sessions"]["day1"]["frames"]["disks"]["450"]["100ms"]["r001"]
        np.testing.assert_array_equal(
            served.read(), read_raw_tiff(session.folder / record["file"])[0]
        )
        spectral = client["recon"]["spectral"].read()
        np.testing.assert_array_equal(spectral["wavelength"].values, WAVELENGTHS_NM)
        image = read_raw_exr(lab_folder / "hdr" / "disks" / "450.exr")
        np.testing.assert_array_equal(client["hdr"]["disks"]["450"].read()["raw"].values, image.raw)
        assert client["lens"].metadata["kind"] == "labkit.dispersion_model"
