"""`labkit.bench.real_frames`: reconstruction rows on the real ColorChecker frames."""

from __future__ import annotations

import pytest

from labkit.bench.harness import Measurement
from labkit.bench.real_frames import MAIN_VARIANTS, comparison_table, real_measurements


def test_real_rows_score_the_default_reconstruction_as_the_demo_does() -> None:
    """The default problem on the vendored frames scores what ``labkit demo --real``
    reports (patch-centre MRAE 0.2018, edge RMSE G 0.134; bilinear's G 0.130, Menon's
    0.119), and the table pairs it with the simulated row of the same variant."""
    rows, baselines = real_measurements(MAIN_VARIANTS[:1])
    (row,) = rows
    assert row.extra["variant"] == "defaults"
    assert row.extra["mrae"] == pytest.approx(0.2018, abs=0.01)
    assert row.extra["edge_rmse_G"] == pytest.approx(0.134, abs=0.01)
    assert row.extra["exact"] > row.extra["patches"] // 2
    assert set(baselines) == {"bilinear", "malvar", "menon"}
    assert baselines["bilinear"][1] == pytest.approx(0.130, abs=0.005)
    assert baselines["menon"][1] == pytest.approx(0.119, abs=0.005)
    simulated = Measurement(
        "sim",
        1.0,
        [1.0],
        0.0,
        extra={"variant": "defaults", "spectral_rmse_rel": 0.08, "spectral_mrae": 0.16,
               "edge_rmse_R": 0.02, "edge_rmse_G": 0.02, "edge_rmse_B": 0.03},
    )  # fmt: skip
    table = comparison_table(rows, [simulated])
    assert table.rows[0][0] == "defaults" and table.rows[0][6] == "0.0800"
    assert len(table.rows[0]) == len(table.columns)
