"""`labkit.bench.real_frames`: reconstruction rows on the real ColorChecker frames."""

from __future__ import annotations

import pytest

from labkit.bench.harness import Measurement
from labkit.bench.real_frames import (
    MAIN_VARIANTS,
    comparison_table,
    patch_cost,
    patch_cost_table,
    real_measurements,
)


def test_real_rows_score_the_default_reconstruction_as_the_demo_does() -> None:
    """The default problem on the vendored frames scores what ``labkit demo --real``
    reports (patch-centre MRAE 0.1980, edge RMSE G 0.1181: below every baseline's, bilinear's
    0.130 and Menon's 0.119; the L2 prior's was 0.134), and the table pairs it with the
    simulated row of the same variant."""
    rows, baselines = real_measurements(MAIN_VARIANTS[:1])
    (row,) = rows
    assert row.extra["variant"] == "defaults"
    assert row.extra["mrae"] == pytest.approx(0.1980, abs=0.005)
    assert row.extra["edge_rmse_G"] == pytest.approx(0.1181, abs=0.004)
    assert row.extra["exact"] > row.extra["patches"] // 2
    assert set(baselines) == {"bilinear", "malvar", "menon"}
    assert baselines["bilinear"][1] == pytest.approx(0.130, abs=0.005)
    assert baselines["menon"][1] == pytest.approx(0.119, abs=0.005)
    assert row.extra["edge_rmse_G"] < min(edge[1] for edge in baselines.values())
    # per pixel against the multispectral image: the chart 0.159; edge strips 0.143,
    # centres 0.107, the frame around the patches 0.196 (without band balance: 0.181,
    # 0.157, 0.112, 0.233; VTV: 0.162, 0.163, 0.138, 0.171)
    assert row.extra["spectral_rmse"] == pytest.approx(0.135, abs=0.008)
    assert row.extra["spectral_rmse_centres"] < row.extra["spectral_rmse_strips"]
    assert row.extra["spectral_rmse_strips"] < row.extra["spectral_rmse_surround"]
    simulated = Measurement(
        "sim",
        1.0,
        [1.0],
        0.0,
        extra={"variant": "defaults", "spectral_rmse_rel": 0.08, "spectral_mrae": 0.16,
               "edge_rmse_R": 0.02, "edge_rmse_G": 0.02, "edge_rmse_B": 0.03},
    )  # fmt: skip
    table = comparison_table(rows, [simulated])
    assert table.rows[0][0] == "defaults" and table.rows[0][8] == "0.0800"
    assert table.rows[0][5] == f"{row.extra['spectral_rmse']:.4f}"
    regions = ("strips", "centres", "surround")
    assert table.rows[0][6].split("/") == [
        f"{row.extra[f'spectral_rmse_{region}']:.4f}" for region in regions
    ]
    assert table.rows[0][-1] == "—"  # the simulated row has no strip errors
    assert len(table.rows[0]) == len(table.columns)

    cost = row.extra["patch_cost"]
    assert cost["patches"] == row.extra["patches"] and 0 < cost["phi_patches"] <= cost["patches"]
    assert cost["samples_median"] > 1  # the real dispersion is sampled at several wavelengths
    assert cost["phi_ms_median"] > cost["phi_formation_ms_median"] > 0
    cost_table = patch_cost_table(rows, [])
    assert [r[:2] for r in cost_table.rows] == [["defaults", "real"]]
    assert len(cost_table.rows[0]) == len(cost_table.columns)


def _record(phi: str, **values: float) -> dict:
    fields = ("samples", "iterations", "polish_rounds", "cg_mean", "seconds", "formation_seconds")
    return {"phi": phi, "exact": values.pop("exact", True), **dict.fromkeys(fields, 0), **values}


def test_patch_cost_separates_patches_with_and_without_phi() -> None:
    records = [
        _record("used", samples=30, iterations=0, polish_rounds=4, seconds=0.1,
                formation_seconds=0.01),
        _record("used", samples=40, iterations=12, polish_rounds=2, seconds=0.3,
                formation_seconds=0.03, exact=False),
        _record("skipped: flat patch", samples=1, polish_rounds=1, seconds=0.02,
                formation_seconds=0.001),
    ]  # fmt: skip
    cost = patch_cost(records)
    assert (cost["patches"], cost["phi_patches"], cost["exact"]) == (3, 2, 2)
    assert (cost["samples_median"], cost["samples_max"]) == (35, 40)
    assert (cost["phi_iterations_median"], cost["phi_iterations_max"]) == (6, 12)
    assert cost["phi_rounds_median"] == 3 and cost["plain_rounds_median"] == 1
    assert cost["phi_ms_median"] == pytest.approx(200) and cost["plain_ms_median"] == pytest.approx(
        20
    )
    assert cost["phi_formation_ms_median"] == pytest.approx(20)
    # no patch without Φ: its columns are empty, not zero
    only_phi = patch_cost(records[:2])
    assert only_phi["plain_ms_median"] != only_phi["plain_ms_median"]  # NaN
    row = Measurement("r", 1.0, [1.0], 0.0, extra={"variant": "v", "patch_cost": only_phi})
    (cells,) = patch_cost_table([row], []).rows
    assert cells[2] == "2 / 0" and cells[8] == "200 / —"
