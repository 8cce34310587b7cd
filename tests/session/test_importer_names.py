"""``session import`` file-name matching: a frame given twice, an exposure without unit."""

from __future__ import annotations

from pathlib import Path

import pytest

from labkit.errors import DataError
from labkit.rig import load_rig
from labkit.session.importer import import_session, match_files

PATTERN = "{scene}_{illumination}_{exposure}_{replicate}.tif"


def _files(folder: Path, *names: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        (folder / name).write_bytes(b"")
    return folder


def test_the_same_frame_in_two_folders_is_refused_naming_both(tmp_path, sim_rig_path):
    rig = load_rig(sim_rig_path)
    a = _files(tmp_path / "a", "disks_450_100ms_1.tif")
    b = _files(tmp_path / "b", "disks_450_100ms_1.tif", "disks_450_100ms_2.tif")
    with pytest.raises(DataError, match=r"a/disks_450_100ms_1.tif and .*b/disks_450_100ms_1"):
        match_files([a, b], [PATTERN], rig)


def test_names_without_replicate_are_numbered_not_refused(tmp_path, sim_rig_path):
    rig = load_rig(sim_rig_path)
    a = _files(tmp_path / "a", "disks_450_100ms_x.tif", "disks_450_100ms_y.tif")
    matched, _ = match_files([a], ["{scene}_{illumination}_{exposure}_*.tif"], rig)
    assert sorted(m.key.replicate for m in matched) == [0, 1]


def test_one_folder_given_twice_is_refused(tmp_path, sim_rig_path):
    rig = load_rig(sim_rig_path)
    a = _files(tmp_path / "a", "disks_450_100ms_1.tif")
    (tmp_path / "link").symlink_to(a)
    with pytest.raises(DataError, match=r"--from .*a is given twice"):
        import_session(tmp_path / "s", [a, a], [PATTERN], rig)
    with pytest.raises(DataError, match=r"--from .*a and --from .*link are the same folder"):
        import_session(tmp_path / "s", [a, tmp_path / "link"], [PATTERN], rig)
    assert not (tmp_path / "s").exists()


def test_an_exposure_without_unit_is_named(tmp_path, sim_rig_path):
    a = _files(tmp_path / "a", "disks_450_100_1.tif")
    with pytest.raises(DataError, match=r"disks_450_100_1.tif, \{exposure\} '100' has no unit"):
        import_session(tmp_path / "s", a, [PATTERN], load_rig(sim_rig_path))
