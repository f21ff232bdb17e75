"""Figures from a small real run of the fakes: expected axes and series, not blank, embedded."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pytest
from idr_core.refiner import RefinerConfig
from matplotlib.image import imread

from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import load_config
from pipeline.reporting import figures as F
from pipeline.reporting import run_data as D
from pipeline.results import aggregate as agg

CONF = Path(__file__).resolve().parents[3] / "conf"
# baseline, diagnose, and E / F at (alpha, tau) = (0.08, cal), (0.5, cal), (0.08, 999): an alpha
# series and a tau series per mode
GRID = (
    "grid=[{mode: [baseline, diagnose, E, F]}, "
    "{alpha: [0.08, 0.5, 0.08], tau: [calibrated, calibrated, 999]}]"
)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("figs") / "run"
    cfg = load_config(
        CONF / "smoke.yaml",
        ["executor.kind=inline", "tracking.enabled=false", "episodes_per_task=2", GRID],
    )
    execute(plan_run(cfg, out))
    return out


@pytest.fixture(scope="module")
def built(run_dir) -> tuple[D.RunData, F.Figures]:
    data = D.load_run(run_dir)
    return data, F.build_figures(data)


def _not_blank(fig, path: Path) -> None:
    F.save(fig, path)
    img = imread(path)[..., :3]
    assert img.shape[0] > 200 and img.shape[1] > 300
    assert img.std() > 0.05  # not a blank canvas
    # the plot area itself holds drawn pixels, not only the frame and labels
    ax = fig.axes[0]
    x0, y0, x1, y1 = ax.get_window_extent().extents.astype(int)
    h = img.shape[0]
    inside = img[h - y1 + 3 : h - y0 - 3, x0 + 3 : x1 - 3]
    assert (inside.std(axis=2) > 0.05).mean() > 0.002 or inside.std() > 0.05


def _legend(ax) -> list[str]:
    return [t.get_text() for t in ax.get_legend().get_texts()]


def test_every_figure_is_built_and_embedded_in_the_report(run_dir, built) -> None:
    _, figs = built
    assert set(figs.built) == set(F.CAPTIONS) and not figs.skipped
    report = (run_dir / "report.md").read_text()
    for name in F.CAPTIONS:
        assert (run_dir / "figures" / f"{name}.png").is_file()
        assert f"(figures/{name}.png)" in report
    assert "## τ calibration" in report


def test_rimg_heatmap_is_the_ratio_of_mean_effects(tmp_path, built) -> None:
    data, figs = built
    fig = figs.built["rimg_heatmap"]
    ax = fig.axes[0]
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("suite", "backbone")
    (image,) = ax.get_images()
    ref = data.steps[data.steps.cell_id == "diagnose"]
    by_hand = ref.e_img.mean() / (ref.e_img.mean() + ref.e_prop.mean() + 1e-6)
    assert image.get_array().shape == (1, 1)
    assert float(image.get_array()[0, 0]) == pytest.approx(by_hand, rel=1e-5)
    assert [t.get_text() for t in ax.texts] == [f"{100 * by_hand:.1f}%"]
    assert [t.get_text() for t in ax.get_yticklabels()] == ["fake_marker"]
    _not_blank(fig, tmp_path / "h.png")


def test_rimg_over_progress_has_baseline_e_f_and_gripper_events(tmp_path, built) -> None:
    data, figs = built
    fig = figs.built["rimg_progress"]
    ax = fig.axes[0]
    assert ax.get_xlabel().startswith("normalized task progress") and ax.get_ylabel() == "R_img"
    events = D.gripper_events(data.steps[data.steps.cell_id == "diagnose"])
    assert events["close"] and events["open"]  # the fake's last action dim changes sign
    labels = _legend(ax)
    assert labels[:3] == [
        "baseline (diagnose: executes a_base)",
        "mode E (E_a0.08_taucal)",
        "mode F (F_a0.08_taucal)",
    ]
    assert labels[3:] == ["gripper close", "gripper open"]
    series = [ln for ln in ax.get_lines() if ln.get_linestyle() == "-"]
    dashed = [ln for ln in ax.get_lines() if ln.get_linestyle() == "--"]
    assert len(series) == 3 and len(dashed) == len(events["close"]) + len(events["open"])
    for ln in series:
        x, y = ln.get_xdata(), ln.get_ydata()
        assert len(x) >= 3 and np.all((x > 0) & (x < 1)) and np.all((y >= 0) & (y <= 1))
    _not_blank(fig, tmp_path / "p.png")


def test_success_vs_alpha_and_tau_with_intervals(tmp_path, built) -> None:
    data, figs = built
    ok = data.episodes[data.episodes.error.isna()]
    for param, ticks, cells in (
        ("alpha", ["0.08", "0.5"], ["E_a0.08_taucal", "E_a0.5_taucal"]),
        ("tau", None, ["E_a0.08_taucal", "E_a0.08_tau999"]),
    ):
        fig = figs.built[f"success_{param}"]
        ax = fig.axes[0]
        symbol = {"alpha": "correction scale α", "tau": "intervention threshold τ"}[param]
        assert (ax.get_xlabel(), ax.get_ylabel()) == (symbol, "success rate (%)")
        assert len(ax.containers) == 2  # one errorbar series per mode (E and F)
        assert _legend(ax) == ["baseline (95% CI)", "mode E", "mode F"]
        tick_text = [t.get_text() for t in ax.get_xticklabels()]
        if ticks:
            assert tick_text == ticks
        else:
            assert tick_text[0].startswith("calibrated\n(") and tick_text[1] == "999"
        e_line = ax.containers[0].lines[0]
        expected = [100 * ok[ok.cell_id == c].success.mean() for c in cells]
        assert list(e_line.get_ydata()) == pytest.approx(expected)
        _not_blank(fig, tmp_path / f"{param}.png")


def test_gate_rate_over_progress_one_line_per_refining_cell(tmp_path, built) -> None:
    data, figs = built
    ax = figs.built["gate_progress"].axes[0]
    assert ax.get_ylabel() == "gate activation rate"
    refining = sorted(c for c in data.steps.cell_id.unique() if c[0] in "EF")
    assert _legend(ax) == refining and len(ax.get_lines()) == 6
    always_on = ax.get_lines()[refining.index("E_a0.08_tau999")].get_ydata()
    assert np.all(always_on == 1.0)  # tau 999: the gate never closes on the fakes
    _not_blank(figs.built["gate_progress"], tmp_path / "g.png")


def test_gripper_events_and_rimg_matrix_by_hand() -> None:
    # two episodes of 10 steps; the gripper closes at step 4 and opens at step 8 in the first,
    # closes at step 6 in the second
    rows = []
    for ep, grips in ((0, [-1, -1, 1, 1, -1]), (1, [-1, -1, -1, 1, 1])):
        for k, g in enumerate(grips):
            rows.append(
                {"cell_id": "d", "task_id": "t", "episode_index": ep, "step": 2 * k, "grip": g}
            )
    steps = pd.DataFrame(rows)
    steps["progress"] = steps["step"] / 10
    assert D.gripper_events(steps) == {"close": [pytest.approx(0.5)], "open": [0.8]}
    effects = pd.DataFrame(
        {
            "backbone": ["a", "a", "b"],
            "suite": ["s", "s", "s"],
            "e_img": [1.0, 3.0, 1.0],
            "e_prop": [3.0, 1.0, 0.0],
        }
    )
    m = D.rimg_matrix(effects)
    # ratio of means (2 / (2 + 2)), not mean of ratios ((0.25 + 0.75) / 2 happens to match:
    # check b too)
    assert m.loc["a", "s"] == pytest.approx(0.5, rel=1e-5)
    assert m.loc["b", "s"] == pytest.approx(1.0, rel=1e-5)


def test_a_grid_without_diagnose_or_sweeps_says_what_is_not_drawn(tmp_path) -> None:
    eps = pd.DataFrame(
        {
            "cell_id": ["baseline", "E"],
            "task_id": ["t", "t"],
            "episode_index": [0, 0],
            "mode": ["baseline", "E"],
            "strategy": ["zero", "zero"],
            "alpha": [0.08, 0.08],
            "beta": [0.05, 0.05],
            "lam": [0.1, 0.1],
            "tau": [7.0, 7.0],
            "guidance": ["visual", "visual"],
            "suite": ["s", "s"],
            "backbone": ["b", "b"],
            "steps": [4, 4],
            "success": [True, False],
            "error": [None, None],
        }
    )
    steps = pd.DataFrame(
        {
            "cell_id": ["E", "E"],
            "task_id": ["t", "t"],
            "episode_index": [0, 0],
            "step": [0, 2],
            "e_img": [1.0, 2.0],
            "e_prop": [1.0, 1.0],
            "r_img": [0.5, 0.66],
            "gate": [1.0, 0.0],
            "grip": [np.nan, np.nan],
        }
    )
    figs = F.build_figures(D.RunData(eps, _progress(steps, eps), {}))
    assert set(figs.built) == {"gate_progress"}
    assert "needs a diagnose cell" in figs.skipped["rimg_heatmap"]
    assert "differ only in alpha" in figs.skipped["success_alpha"]


def _gripper_events_by_loop(steps: pd.DataFrame) -> dict[str, list[float]]:
    """The definition, one episode at a time."""
    found: dict[str, dict[int, list[float]]] = {"close": {}, "open": {}}
    df = steps.dropna(subset=["grip"]).sort_values([*D.KEY, "step"])
    for _, g in df.groupby(D.KEY, sort=False):
        closed = g["grip"].to_numpy() > 0
        prog = g["progress"].to_numpy()
        counts = {"close": 0, "open": 0}
        for i in np.flatnonzero(closed[1:] != closed[:-1]) + 1:
            kind = "close" if closed[i] else "open"
            counts[kind] += 1
            if counts[kind] <= D.MAX_EVENTS:
                found[kind].setdefault(counts[kind], []).append(float(prog[i]))
    return {k: [float(np.median(v)) for _, v in sorted(ks.items())] for k, ks in found.items()}


def test_gripper_events_equal_the_per_episode_definition() -> None:
    rng = np.random.default_rng(5)
    rows = []
    for e in range(300):
        n = int(rng.integers(1, 40))
        grip = np.where(rng.random(n) < 0.15, np.nan, rng.choice([-1.0, 1.0], n, p=[0.7, 0.3]))
        for k in range(n):
            rows.append(
                {
                    "cell_id": "diagnose",
                    "task_id": f"t{e % 3}",
                    "episode_index": e,
                    "step": 4 * k,
                    "grip": grip[k],
                    "progress": k / n,
                }
            )
    steps = pd.DataFrame(rows).sample(frac=1.0, random_state=1)  # any order
    got, want = D.gripper_events(steps), _gripper_events_by_loop(steps)
    assert got.keys() == want.keys() and all(len(got[k]) > 1 for k in got)
    for kind in want:
        assert got[kind] == pytest.approx(want[kind])
    assert D.gripper_events(steps.iloc[:0]) == {"close": [], "open": []}


def test_a_sweep_with_a_cell_at_100_percent_is_drawn() -> None:
    """Wilson's upper bound at 10/10 is 0.9999999999999999: the error bar must not go below 0
    (matplotlib refuses negative yerr; the τ grid's figure failed on it)."""
    lo, hi = agg.wilson(10, 10)
    assert hi < 1.0  # the rounding the figure has to tolerate
    table = pd.DataFrame(
        {
            "x": [0.5, 1.0],
            "label": ["0.5", "1"],
            "series": ["mode=E, alpha=0.08", "mode=E, alpha=0.08"],
            "success": [1.0, 0.9],
            "ci_low": [lo, agg.wilson(9, 10)[0]],
            "ci_high": [hi, agg.wilson(9, 10)[1]],
        }
    )
    fig = F.success_sweep(table, "tau")
    (line,) = [c for c in fig.axes[0].containers]
    assert list(line.lines[0].get_ydata()) == [100.0, 90.0]


def _progress(steps: pd.DataFrame, episodes: pd.DataFrame) -> pd.DataFrame:
    """``progress_table`` for pandas frames."""
    as_table = pa.Table.from_pandas
    return D.progress_table(
        as_table(steps, preserve_index=False), as_table(episodes, preserve_index=False)
    ).to_pandas()


def test_the_cell_standing_for_a_mode_is_at_the_configs_declared_alpha(tmp_path) -> None:
    cells = pd.DataFrame(
        {
            "cell_id": ["diagnose", "E_a0.08", "E_a0.2"],
            "mode": ["diagnose", "E", "E"],
            "strategy": ["zero"] * 3,
            "alpha": [0.08, 0.08, 0.2],
        }
    )
    assert F.pick_cell(cells, "E", "zero", {}, alpha=0.2) == "E_a0.2"
    assert F.pick_cell(cells, "E", "zero", {}, alpha=0.08) == "E_a0.08"
    (tmp_path / "config.yaml").write_text("idr: {alpha: 0.2, tau: calibrated}\n")
    assert D.declared_alpha(tmp_path) == 0.2
    (tmp_path / "config.yaml").write_text("idr: {tau: calibrated}\n")
    assert D.declared_alpha(tmp_path) == RefinerConfig().alpha  # the refiner's (paper's) default
