"""`results`: the tiny preset runs every job from scratch and writes Markdown tables and figures whose numbers are the
MLflow runs', the batches' episodes' and the ceiling's worlds'; planner seeds that were the dataset's are refused."""
import csv
import re
from pathlib import Path

import mlflow
import numpy as np
import pytest
from test_batch import wilson_by_roots

from bench import results
from bench.results_tables import beaten, outcome_table
from conftest import compose_cfg
from data.dataset import episode_seeds
from planner.compare import fmt


def test_planner_seeds_that_were_dataset_episodes_are_refused(tmp_path, capsys):
    taken = episode_seeds(0, 40)[3]  # the tiny dataset's fourth episode
    cfg = compose_cfg("results", ["results_preset=tiny", f"planner_seed={taken - 1}", f"out_dir={tmp_path}"])
    with pytest.raises(SystemExit) as e:
        results.run(cfg)
    assert e.value.code == 2 and f"world seeds [{taken}] are episodes of the dataset tiny" in capsys.readouterr().err
    cfg = compose_cfg("results", ["results_preset=tiny", "planner_seed=999999", f"out_dir={tmp_path}"])
    with pytest.raises(SystemExit):  # 999999 + 3 reaches the interaction benchmark's worlds from 10**6
        results.run(cfg)


def section(md: str, title: str) -> str:
    """The text of the Markdown section `## title`, up to the next one."""
    return md.split(f"## {title}\n")[1].split("\n## ")[0]


def cell(md: str, title: str, first: str, second: str, column: int) -> str:
    """The `column`-th cell of the row starting | first | second | in section `title`."""
    row = next(line for line in section(md, title).splitlines() if line.startswith(f"| {first} | {second} |"))
    return row.split("|")[1:-1][column].strip()


def numbers(text: str) -> list[float]:
    """The decimal numbers of a cell: [value] or [value, lo, hi]."""
    return [float(x) for x in re.findall(r"-?\d+\.\d+", text)]


def rate_cell(values) -> list[float]:
    """What a rate cell must show for 0/1 values, in %: the share and its Wilson interval (by the score test's roots)."""
    k, n = float(np.sum(values)), len(values)
    return [100 * k / n, *(100 * np.array(wilson_by_roots(k, n)))]


def episodes_csv(folder: str, method: str) -> list[dict]:
    """The finished episodes of a batch's per-episode CSV."""
    rows = csv.DictReader(open(next(Path(folder).glob(f"episodes_{method}_*.csv"))))
    return [{k: float(v) for k, v in r.items() if k not in ("error", "notes")} for r in rows if r["crash"] == "0"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """(report folder, work folder, Markdown, report's arguments (cfg, jobs' results, batches, work, dest)) of one run of
    the tiny preset."""
    root = tmp_path_factory.mktemp("results")
    seen, report = [], results.report

    def keep(*args):
        seen.extend(args)
        return report(*args)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(results, "report", keep)
        path = results.run(compose_cfg("results", ["results_preset=tiny", f"out_dir={root / 'out'}",
                                                   f"work_dir={root / 'work'}", "n_jobs=1"]))
    return root / "out", root / "work", path.read_text(), seen


@pytest.mark.slow  # the tiny preset's whole results run (module fixture `tiny`)
def test_tiny_preset_writes_tables_and_figures_matching_mlflow(tiny):
    out, work, md, _ = tiny
    for f in ("b_imposed.png", "fidelity.png", "merge_rate.png", "t_merge.png", "fallbacks.png", "accuracy_vs_speed.png",
              "snapshots_admm.png"):
        assert (out / f).read_bytes()[:4] == b"\x89PNG" and f in md
    assert (out / "merge_admm.gif").read_bytes()[:3] == b"GIF"
    planner = mlflow.search_runs(experiment_names=["planner"])
    work = str(work)
    mine = planner[planner["params.out_dir"].str.startswith(work)]
    for source in ("cv", "student"):  # one training: the pooled rates are the batch run's own
        for method in ("admm", "nnmpc"):
            r = mine[(mine["params.scenario"] == "random") & (mine["params.gradients"] == source)
                     & (mine["params.method"] == method)]
            assert len(r) == 1 and r["metrics.episodes"].iloc[0] == 4
            episodes = csv.DictReader(open(next(Path(r["params.out_dir"].iloc[0]).glob(f"episodes_{method}_*.csv"))))
            merged = [float(e["merged"]) for e in episodes if e["crash"] == "0"]
            k, n = sum(merged), len(merged)
            shown = [float(x) for x in re.findall(r"\d+\.\d", cell(md, "Random merges", source, method.upper(), 3))]  # %
            assert shown == pytest.approx([100 * k / n, *(100 * np.array(wilson_by_roots(k, n)))], abs=0.051)
            assert cell(md, "Random merges", source, method.upper(), 2) == f"1 x {n}"
    distill = mlflow.search_runs(experiment_names=["distill"])
    teacher = distill[(distill["params.models_dir"].str.startswith(work)) & (distill["params.model"] == "teacher")]
    assert len(teacher) == 1
    ade = 1e3 * teacher["metrics.ade_rollout_m"].iloc[0]
    row = next(line for line in md.splitlines() if line.startswith("| teacher |"))
    assert float(row.split("|")[3]) == pytest.approx(ade, abs=0.051)
    inter = mlflow.search_runs(experiment_names=["interaction"])
    student = inter[(inter["params.models_dir"].str.startswith(work)) & (inter["params.source"] == "student")]
    section = md.split("## Interaction fidelity\n")[1]
    row = next(line for line in section.splitlines() if line.startswith("| student | "))
    assert float(row.split("|")[5]) == pytest.approx(student["metrics.react_corr_jac"].iloc[0], abs=5e-4)
    assert np.isfinite(float(row.split("|")[2]))


@pytest.mark.slow  # the tiny preset's whole results run (module fixture `tiny`)
def test_tiny_dense_headline_matches_the_per_world_csvs(tiny):
    _, work, md, _ = tiny
    assert md.index("## Dense traffic (headline)") < md.index("## Ceiling calibration") < md.index("## Predictors")
    worlds = {sc: list(csv.DictReader(open(work / "ceiling" / f"ceiling_{sc}.csv")))
              for sc in ("dense", "random", "two_lane", "three_lane")}
    assert [len(w) for w in worlds.values()] == [2, 2, 1, 1]  # tiny: dense_episodes, calibration_episodes, table2_episodes
    dense = [{k: float(v) for k, v in w.items() if not k.endswith("_policy")} for w in worlds["dense"]]
    assert [w["seed"] for w in dense] == [2000000, 2000001]  # the planner's held-out worlds
    planner = mlflow.search_runs(experiment_names=["planner"])
    mine = planner[planner["params.out_dir"].str.startswith(str(work)) & (planner["params.scenario"] == "dense")]
    recording = mine["params.out_dir"].str.startswith(str(work / "runs" / "iterates-"))  # the surrogate's states, not a row
    assert recording.sum() == 1 and set(mine[recording]["params.seed"]) == {"5000000"}
    mine = mine[~recording & (mine["params.scenario.cooperation"] == "mixed")]  # not the cooperation sweep's
    best = {w["seed"]: w["ceiling_t_merge"] if w["ceiling_courteous"] else np.inf for w in dense}
    beat = set()
    for source, mpc, method in [(s, "paper", m) for s in ("cv", "student") for m in ("admm", "nnmpc")] + \
            [(s, "courteous", "admm") for s in ("cv", "student")]:  # an mpc option's rows: ADMM alone
        r = mine[(mine["params.gradients"] == source) & (mine["params.method"] == method) & (mine["params.mpc"] == mpc)]
        assert len(r) == 1
        eps = episodes_csv(r["params.out_dir"].iloc[0], method)
        assert [e["seed"] for e in eps] == [2000000, 2000001]
        name = source if mpc == "paper" else f"{source} {mpc}"
        row = lambda c: numbers(cell(md, "Dense traffic (headline)", name, method.upper(), c))
        assert cell(md, "Dense traffic (headline)", name, method.upper(), 2) == "1 x 2"
        assert row(3) == pytest.approx(rate_cell([e["courteous"] for e in eps]), abs=0.051)
        assert row(4) == pytest.approx(rate_cell([e["merged"] for e in eps]), abs=0.051)
        assert row(6)[0] == pytest.approx(np.mean([e["b_imposed_max"] for e in eps]), abs=0.0051)
        assert row(7) == pytest.approx(rate_cell([e["collision"] for e in eps]), abs=0.051)
        beat |= {e["seed"] for e in eps if e["courteous"] and e["t_merge"] < best[e["seed"]]}
    assert "blind_courteous" not in worlds["random"][0]  # the best fixed strategy: the dense worlds' alone
    assert {w["blind_policy"] for w in worlds["dense"]} == {w["blind_policy"] for w in worlds["dense"][:1]}  # one for all
    for search, name in (("ceiling", "ceiling"), ("never_yield", "never-yield ceiling"), ("blind", "best fixed strategy")):
        row = lambda c: cell(md, "Dense traffic (headline)", name, "-", c)
        hits = [w[f"{search}_courteous"] for w in dense]
        assert numbers(row(3)) == pytest.approx(rate_cell(hits), abs=0.051)
        t = [w[f"{search}_t_merge"] for w in dense if w[f"{search}_courteous"]]
        assert (numbers(row(5))[:1] == pytest.approx([np.mean(t)], abs=0.051)) if t else row(5) == "-"
        assert numbers(row(6))[0] == pytest.approx(np.mean([w[f"{search}_b_imposed"] for w in dense]), abs=0.0051)
        assert row(4) == row(7) == row(8) == "-"  # the search neither reports plain merges, collisions nor fallbacks
    # every planner run was one of the ceiling's starts: none beats it, and the report says how often the search alone sufficed
    steps = sorted((work / "planner" / "dense").glob("*/*/steps/*.csv"))
    assert beat == set() and "planner beat the ceiling on 0 worlds of 2" in md
    assert [w["starts"] for w in dense] == [sum(f.stem.endswith(f"_{w['seed']:.0f}") for f in steps) for w in dense] == [10, 8]
    assert cell(md, "Dense traffic (headline)", "oracle interactive", "ADMM", 2) == "1 x 1"  # the oracle row: the first world
    assert cell(md, "Dense traffic (headline)", "oracle interactive 8 cars", "ADMM", 2) == "1 x 1"  # ... seeing 8 cars
    reached = sum(w["search_courteous"] == w["ceiling_courteous"] and w["search_t_merge"] == w["ceiling_t_merge"] for w in dense)
    assert f"already reached the final value on {reached} of the 2 worlds" in md
    for f in steps:  # a run's per-step CSV: a row per step it drove
        method, seed = f.stem.split("_")
        (e,) = [e for e in episodes_csv(str(f.parents[1]), method) if e["seed"] == float(seed)]
        assert len(list(csv.DictReader(open(f)))) == e["steps"]
    paired = {line.split("|")[1].strip(): line.split("|")[2].strip() for line in md.split("Time to merge against")[1]
              .split("Where each ADMM row")[0].splitlines() if line.startswith("| ") and "---" not in line}
    for row, method in (("cv", "admm"), ("cv courteous", "admm")):
        eps = [e for f in (work / "planner" / "dense" / row).glob("*") for e in episodes_csv(str(f), method)]
        pairs = sum(bool(e["courteous"]) and best[e["seed"]] < np.inf for e in eps)
        assert paired[f"{row} {method.upper()}"] == str(pairs)
    for sc, rows in worlds.items():
        row = lambda c: cell(md, "Ceiling calibration", sc, str(len(rows)), c)
        assert numbers(row(2)) == pytest.approx(rate_cell([float(w["ceiling_courteous"]) for w in rows]), abs=0.051)
        assert numbers(row(3)) == pytest.approx(rate_cell([float(w["never_yield_courteous"]) for w in rows]), abs=0.051)
        assert numbers(row(5)) == pytest.approx([max(float(w["held_b_imposed"]) for w in rows)], abs=0.0051)
    header = next(line for line in section(md, "Table II: two_lane").splitlines() if line.startswith("| gradients |"))
    header = [h.strip() for h in header.split("|")[1:-1]]
    assert header[3:5] == ["courteous % [95% CI]", "merged % [95% CI]"]
    (w,) = worlds["two_lane"]
    shown = cell(md, "Table II: two_lane", "cv", "ADMM", header.index("ceiling t_merge steps [95% CI]"))
    assert shown == (f"{float(w['ceiling_t_merge']):.1f}" if float(w["ceiling_courteous"]) else "-")
    table2 = planner[planner["params.out_dir"].str.startswith(str(work / "planner" / "two_lane"))]  # not the showcase
    for mpc, method in [("paper", "admm"), ("paper", "nnmpc"), ("courteous", "admm")]:  # an mpc option's rows: ADMM alone
        r = table2[(table2["params.gradients"] == "cv") & (table2["params.mpc"] == mpc) & (table2["params.method"] == method)]
        assert len(r) == 1
        (e,) = episodes_csv(r["params.out_dir"].iloc[0], method)
        name = "cv" if mpc == "paper" else "cv courteous"
        assert numbers(cell(md, "Table II: two_lane", name, method.upper(), 3)) == pytest.approx(rate_cell([e["courteous"]]),
                                                                                                abs=0.051)


def test_a_planner_beats_the_ceiling_with_a_courteous_merge_it_missed_or_made_later():
    worlds = [{"seed": 1, "ceiling_courteous": 1.0, "ceiling_t_merge": 20.0},
              {"seed": 2, "ceiling_courteous": 0.0, "ceiling_t_merge": 60.0},
              {"seed": 3, "ceiling_courteous": 1.0, "ceiling_t_merge": 20.0}]
    episodes = [{"seed": 1, "courteous": 1.0, "t_merge": 19.0}, {"seed": 2, "courteous": 1.0, "t_merge": 59.0},
                {"seed": 3, "courteous": 1.0, "t_merge": 20.0}]
    assert beaten(worlds, episodes) == {1, 2}
    assert beaten(worlds, [dict(e, courteous=0.0) for e in episodes]) == set()  # a forced merge beats nothing


@pytest.mark.slow  # the tiny preset's whole results run (module fixture `tiny`)
def test_gradients_table_shows_the_surrogate_jobs_scores_of_every_source_with_their_intervals(tiny):
    _, work, md, _ = tiny
    runs = mlflow.search_runs(experiment_names=["surrogate"])
    (job,) = [r for _, r in runs.iterrows() if str(r["params.models_dir"]).startswith(str(work))]  # one training
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]]
            for line in section(md, "Gradients").splitlines() if line.startswith("| ") and "---" not in line}
    for name, suffix in (("surrogate", ""), ("student", "_student"), ("constant velocity (baseline)", "_cv"),
                         ("mean Jacobian (baseline)", "_mean")):
        for column, score in ((2, "grad_rel_err"), (3, "react_rel_err"), (5, "ramp_grad_rel_err")):
            mean, lo, hi = (job[f"metrics.{score}{suffix}{end}"] for end in ("", "_lo", "_hi"))
            assert numbers(rows[name][column]) == pytest.approx([mean, lo, hi] if hi > lo else [mean], abs=5e-4), (name, score)
    assert numbers(rows["constant velocity (baseline)"][3])[0] == pytest.approx(1.0, abs=1e-3)  # cv: no reaction at all


@pytest.mark.slow  # the tiny preset's whole results run (module fixture `tiny`)
def test_each_section_keeps_its_intervals_when_sections_are_added_or_reordered(tiny, tmp_path):
    _, _, md, args = tiny
    report = results.Report(*args[:4], tmp_path)
    assert results.render(report) == md  # the published report, rendered again from the same jobs
    alone = {name: results.render(report, [(name, fn)]) for name, fn in results.SECTIONS}
    assert re.search(r"\[\d+\.\d+, \d+\.\d+\]", alone["dense"] + alone["random"])  # there are bootstrap intervals to move

    def added(r):  # a new section, first, bootstrapping the random merges' episodes again
        return {"table": "\n".join(outcome_table(r.batch_rows("random", r.p.sources)))}

    prose = {**results.texts(), "added": "## Added\n\n{table}\n"}
    shuffled = results.render(results.Report(*args[:4], tmp_path), [("added", added), *results.SECTIONS[::-1]], prose)
    for name, text in alone.items():
        assert text in shuffled, name


def table(md: str) -> tuple[list[str], list[list[str]]]:
    """The header and rows of the first Markdown table in `md`, cells stripped."""
    rows = [[c.strip() for c in line.split("|")[1:-1]] for line in md.splitlines() if line.startswith("| ")]
    return rows[0], rows[1:]


def test_readme_headline_cells_are_the_generated_reports_cells():
    """Every cell of the README's headline table is the generated dense headline's, under the same column name."""
    root = Path(__file__).parents[1]
    header, rows = table(section((root / "README.md").read_text(), "The headline"))
    full, generated = table(section((root / "results" / "README-results.md").read_text(), "Dense traffic (headline)"))
    assert header[:2] == ["gradients", "method"] and set(header) <= set(full) and len(rows) >= 5
    by_row = {(r[0], r[1]): dict(zip(full, r)) for r in generated}
    for r in rows:  # every figure copied, none typed
        assert (r[0], r[1]) in by_row, r
        assert dict(zip(header, r)) == {h: by_row[(r[0], r[1])][h] for h in header}, r


@pytest.mark.slow  # the tiny preset's whole results run (module fixture `tiny`)
def test_tiny_cooperation_sweep_shows_each_levels_ceiling_and_rows_on_the_same_worlds(tiny):
    out, work, md, _ = tiny
    assert (out / "cooperation.png").read_bytes()[:4] == b"\x89PNG" and "cooperation.png" in md
    header = [h.strip() for h in next(line for line in section(md, "Cooperation sweep").splitlines()
                                      if line.startswith("| row |")).split("|")[1:-1]]
    assert header[1:] == [f"{c}: courteous % [95% CI]" for c in ("stubborn", "mixed", "willing")]
    for i, level in enumerate(("stubborn", "mixed", "willing"), start=1):
        folder = work / "ceiling" / ("" if level == "mixed" else f"dense_{level}")
        worlds = list(csv.DictReader(open(folder / "ceiling_dense.csv")))[:1]  # tiny: 1 world per level, the first
        assert worlds[0]["seed"] == "2000000"
        for search, name in (("ceiling", "ceiling"), ("never_yield", "never-yield ceiling")):
            shown = next(line for line in section(md, "Cooperation sweep").splitlines() if line.startswith(f"| {name} |"))
            assert numbers(shown.split("|")[1:-1][i]) == pytest.approx(rate_cell([float(w[f"{search}_courteous"])
                                                                                  for w in worlds]), abs=0.051)
        batch = work / "planner" / ("dense" if level == "mixed" else f"dense_{level}") / "student courteous" / "seed0"
        eps = [e for e in episodes_csv(str(batch), "admm") if e["seed"] == 2000000]
        shown = next(line for line in section(md, "Cooperation sweep").splitlines() if line.startswith("| student courteous ADMM |"))
        assert numbers(shown.split("|")[1:-1][i]) == pytest.approx(rate_cell([e["courteous"] for e in eps]), abs=0.051)
    stubborn = list(csv.DictReader(open(work / "ceiling" / "dense_stubborn" / "ceiling_dense.csv")))
    assert [w["ceiling_courteous"] for w in stubborn] == [w["never_yield_courteous"] for w in stubborn]  # nobody yields


def test_spearman_rank_correlation_and_its_world_bootstrap_match_a_direct_computation():
    from bench.results_tables import rank_correlation, world_hits

    fidelity = [0.50, 0.87, 0.91, 0.96]  # cv, analytic, teacher, student: no ties
    courteous = {"cv": [0, 0, 0, 1, 0, 0], "analytic": [1, 0, 0, 1, 0, 1], "teacher": [1, 1, 0, 1, 1, 0],
                 "student": [1, 1, 1, 1, 0, 1]}  # per world 2000000..2000005, one training
    rows = {name: [{"seed": 2000000 + j, "courteous": float(c)} for j, c in enumerate(v)] for name, v in courteous.items()}
    rows["student"].append({"seed": 2000002, "courteous": 0.0})  # a second training on one world: 2 episodes there
    hits, counts = world_hits(rows, range(2000000, 2000006))
    assert counts.sum() == 25 and hits[3, 2] == 1 and counts[3, 2] == 2

    def spearman(x, y):  # Pearson's correlation of mean ranks (ties share theirs); nan for a constant side
        rank = lambda v: np.array([sum(u < w for u in v) + (sum(u == w for u in v) + 1) / 2 for w in v])
        rx, ry = rank(x), rank(y)
        if rx.std() == 0 or ry.std() == 0:
            return np.nan
        return float(((rx - rx.mean()) * (ry - ry.mean())).mean() / (rx.std() * ry.std()))

    rates = lambda worlds: [sum(e["courteous"] for e in rows[n] if e["seed"] - 2000000 in worlds)
                            / sum(e["seed"] - 2000000 in worlds for e in rows[n]) for n in rows]
    assert rates(range(6)) == pytest.approx([1 / 6, 0.5, 4 / 6, 5 / 7])
    rho, lo, hi = rank_correlation(fidelity, hits, counts, 400, np.random.default_rng(3))
    assert rho == pytest.approx(spearman(fidelity, rates(range(6)))) == pytest.approx(1.0)
    draws, rng = [], np.random.default_rng(3)
    for _ in range(400):  # core.stats.bootstrap's draws: the one group (all worlds), then the worlds with replacement
        rng.integers(1, size=1)
        worlds = list(rng.integers(6, size=6))  # a world drawn twice counts twice
        draws.append(spearman(fidelity, [sum(hits[i, w] for w in worlds) / sum(counts[i, w] for w in worlds)
                                         for i in range(4)]))
    assert [lo, hi] == pytest.approx(np.nanpercentile(draws, [2.5, 97.5]))
    assert lo < rho == hi == pytest.approx(1.0)
    assert np.isnan(rank_correlation([0.5], hits[:1], counts[:1], 10, np.random.default_rng(0))[0])
    assert np.isnan(rank_correlation(fidelity, 0 * hits, counts, 10, np.random.default_rng(0))).all()  # nobody merges


@pytest.mark.slow  # the tiny preset's whole results run (module fixture `tiny`)
def test_tiny_fidelity_section_puts_each_predictor_s_interactive_batch_beside_its_interaction_scores(tiny):
    _, work, md, (_, out, _, _, _) = tiny
    text = section(md, "Fidelity against outcome")
    assert "![fidelity against outcome](fidelity.png)" in text
    rows = {}
    for source in ("cv", "student"):  # tiny's fidelity_sources: the interactive step on the headline's 2 worlds
        name = f"{source} interactive"
        eps = [e for f in (work / "planner" / "dense" / name).glob("*") for e in episodes_csv(str(f), "admm")]
        assert [e["seed"] for e in eps] == [2000000, 2000001]
        assert numbers(cell(md, "Fidelity against outcome", name, "1 x 2", 5)) == pytest.approx(
            rate_cell([e["courteous"] for e in eps]), abs=0.051)
        judged = next(r for r in csv.DictReader(open(work / "verdicts" / "verdicts.csv")) if r["source"] == source)
        kept = [float(judged[f"good_kept{e}"]) for e in ("", "_lo", "_hi")]  # one training: the job's own interval
        assert kept == pytest.approx([1 - float(judged["false_alarm"]), 1 - float(judged["false_alarm_hi"]),
                                      1 - float(judged["false_alarm_lo"])], abs=2e-4, nan_ok=True)  # NaN: no good merge
        assert cell(md, "Fidelity against outcome", name, "1 x 2", 4) == fmt(
            out["verdicts"][source]["good_kept"], ".3f", out["verdicts"][source]["good_kept_lo"],
            out["verdicts"][source]["good_kept_hi"])
        shown = next(line for line in section(md, "Interaction fidelity").splitlines() if line.startswith(f"| {source} |"))
        for column, score in ((2, "brake_auc"), (3, "react_corr")):
            mine = cell(md, "Fidelity against outcome", name, "1 x 2", column)
            assert mine == shown.split("|")[1:-1][{"brake_auc": 8, "react_corr": 1}[score]].strip(), score
        auc = numbers(shown.split("|")[1:-1][8])  # none ('-'): no state of the tiny set forces anyone to brake
        rows[name] = (float(auc[0]) if auc else np.nan, np.mean([e["courteous"] for e in eps]))
    scored = [v for v in rows.values() if np.isfinite(v[0])]
    rho = "-"  # two predictors: rho is the sign of their order's agreement, none for a tie or with fewer
    if len(scored) == 2 and scored[0][0] != scored[1][0] and scored[0][1] != scored[1][1]:
        rho = f"{np.sign((scored[1][0] - scored[0][0]) * (scored[1][1] - scored[0][1])):.2f}"
    assert f"brake_auc: rho = {rho} over {len(scored)} predictors" in text
    assert "good_kept: rho = " in text and f"{out['verdicts']['oracle']['states']} states, one every 2 steps" in text
