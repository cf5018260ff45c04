"""The paper suite: plan validation, the tables' arithmetic on hand-made records, the claims,
and `run_paper` end to end on the tiny preset (every table and figure written; a rerun reuses
finished experiments and redoes only a missing one; cached baselines are picked up)."""

import json

import numpy as np
import pytest

from safecdt_jax import envs
from safecdt_jax.paper import PaperPlan, experiments, quick_plan, run_paper
from safecdt_jax.paper import tables as T
from safecdt_jax.paper.report import claims
from safecdt_jax.paper.run import baselines_folder, checkpoint_identity


def _run(variant, budget, cost, violation=None, ret=None):
    cost = np.asarray(cost, np.float64)
    return {"variant": variant, "budget": budget, "metrics": {
        "cost": cost.tolist(), "return": (np.zeros_like(cost) if ret is None else ret).tolist(),
        "violation": ((cost > budget) if violation is None else violation).astype(float).tolist(),
        "ctg_target": np.full_like(cost, 0.0).tolist()}}


def test_plan_rejects_bad_values_naming_the_field():
    with pytest.raises(ValueError, match=r"PaperPlan\.pairs: unknown pair XX"):
        PaperPlan(pairs=("XX",))
    with pytest.raises(ValueError, match=r"PaperPlan\.intervention_episodes"):
        PaperPlan(intervention_episodes=51)
    with pytest.raises(ValueError, match=r"PaperPlan\.main_seeds"):
        PaperPlan(main_seeds=0)
    with pytest.raises(ValueError, match=r"PaperPlan\.alpha"):
        PaperPlan(alpha=1.5)


def test_experiments_of_the_default_plan():
    exps = {e.key: e for e in experiments(PaperPlan())}
    assert len(exps) == 3 * 4 + 1  # main, ctg, source_ctg, baselines per pair; studies once
    # Rows of 15 and 3 runs: 3 pretrained checkpoints x 5 and x 1 deployment seeds.
    assert (exps["CG1-CG2_main"].seeds, exps["CG1-CG2_main"].pretrain_seeds) == (5, 3)
    assert (exps["CC1-CC2_main"].seeds, exps["CG1-CG2_studies"].seeds) == (1, 1)
    assert experiments(PaperPlan(pretrain_seeds=5))[0].seeds == 3  # 5 x 3
    # Tables 5 and 6 and the certificate pool the checkpoints too: 3 x 2 and 3 x 1 runs
    assert (exps["CG1-CG2_ctg"].pretrain_seeds, exps["CG1-CG2_ctg"].seeds) == (3, 2)
    assert (exps["PC1-PC2_source_ctg"].pretrain_seeds, exps["PC1-PC2_source_ctg"].seeds) == (3, 1)
    one = {e.key: e for e in experiments(PaperPlan(pretrain_seeds=1))}
    assert one["CG1-CG2_main"].seeds == 15 and one["CC1-CC2_main"].seeds == 3
    studies = exps["CG1-CG2_studies"].runs
    assert [b for v, b in studies if v == "safe_cdt"] == [25.0, 30.0, 35.0, 40.0, 50.0]
    assert [v for v, _ in studies if v != "safe_cdt"] == ["no_reweight", "scheduler_only",
                                                         "zero_shot", "naive_lora"]
    ctg = exps["PC1-PC2_ctg"]
    assert ctg.episodes == 100 and [v for v, _ in ctg.runs][-2:] == [
        "step_change(0.2,1)", "step_change(1,0.2)"]
    assert exps["PC1-PC2_source_ctg"].task == "source"


def test_spec_records_how_lora_ran_only_where_it_changes_bits():
    """A LoRA experiment's spec names its labels and whether its seeds' LoRA gradients ran in
    turn (as this CPU resolves it); an experiment without LoRA shares its record across both."""
    from safecdt_jax.paper.run import experiment_spec

    ckpt = {"task": "CarGoal1", "preset": "cpu", "step": 1, "data": "x"}
    exps = {e.key: e for e in experiments(PaperPlan())}
    main, ctg = exps["CG1-CG2_main"], exps["CG1-CG2_ctg"]  # with LoRA; fixed ratios only
    stage, hindsight = PaperPlan(lora_labels="stage"), PaperPlan(lora_labels="hindsight")
    spec = experiment_spec(main, stage, ckpt)
    assert (spec["lora_in_turn"], spec["lora_labels"]) == (True, "stage")  # one CPU device
    assert experiment_spec(main, hindsight, ckpt) == {**spec, "lora_labels": "hindsight"}
    # "auto" is recorded as the rule it runs: target acting with samples (the default), stage
    # with the mean; under "checkpoint" the checkpoint's identity decides, so it stays "auto"
    rule = {act: experiment_spec(main, PaperPlan(act=act), ckpt)["lora_labels"]
            for act in ("sample", "mean", "checkpoint")}
    assert rule == {"sample": "target", "mean": "stage", "checkpoint": "auto"}
    assert experiment_spec(main, PaperPlan(), ckpt) == experiment_spec(
        main, PaperPlan(act="sample", lora_labels="target"), ckpt)
    assert "lora_labels" not in experiment_spec(ctg, stage, ckpt)
    # an adapting run's spec holds every scheduler and LoRA setting: a changed default is a
    # new experiment; the fixed-target runs of Tables 5 and 6 depend on none of them
    from safecdt_jax.deploy.config import DeployConfig
    assert spec["deploy_config"]["lora_lr"] == DeployConfig().lora_lr
    assert spec["deploy_config"]["cr_step"] == DeployConfig().cr_step
    assert "deploy_config" not in experiment_spec(ctg, stage, ckpt)
    # a field added later is in the spec at a value other than the one that reproduces the
    # records made before it, and stays out at that value (so those records are reused)
    assert spec["deploy_config"]["replay_excess"] == "projected"
    paper_rule = experiment_spec(main, PaperPlan(replay_excess="realised"), ckpt)
    assert "replay_excess" not in paper_rule["deploy_config"]
    assert {k: v for k, v in spec["deploy_config"].items() if k != "replay_excess"} == \
        paper_rule["deploy_config"]
    with pytest.raises(ValueError, match=r"PaperPlan\.replay_excess"):
        PaperPlan(replay_excess="luck")
    assert experiment_spec(ctg, stage, ckpt) == experiment_spec(ctg, hindsight, ckpt)
    with pytest.raises(ValueError, match=r"PaperPlan\.lora_labels"):
        PaperPlan(lora_labels="luck")


def test_acting_mode_is_in_the_spec_unless_the_checkpoints_own_and_reaches_the_deployment(
        monkeypatch, tmp_path):
    """`PaperPlan.act` other than "checkpoint" enters every deployment's spec (the fixed-ratio
    ones too: how the CDT acts decides every rollout), never the baselines'; "checkpoint"
    leaves the older specs as they were; `_run_deploy` hands the mode to the deployment."""
    import safecdt_jax.deploy.job as job
    from safecdt_jax.paper.run import _run_deploy, experiment_spec

    ckpt = {"task": "CarGoal1", "preset": "cpu", "step": 1, "data": "x"}
    exps = {e.key: e for e in experiments(PaperPlan())}
    for key in ("CG1-CG2_ctg", "CG1-CG2_source_ctg"):
        own = experiment_spec(exps[key], PaperPlan(act="checkpoint"), ckpt)
        assert "act" not in own
        assert experiment_spec(exps[key], PaperPlan(), ckpt) == {**own, "act": "sample"}
    base = exps["CG1-CG2_baselines"]
    assert experiment_spec(base, PaperPlan(act="mean"), ckpt) == \
        experiment_spec(base, PaperPlan(), ckpt)
    with pytest.raises(ValueError, match=r"PaperPlan\.act must be one of checkpoint, mean"):
        PaperPlan(act="greedy")
    seen = []
    monkeypatch.setattr(job, "run_deployment", lambda *a, **k: seen.append(
        k["stochastic_actions"]) or {"runs": []})
    main = exps["CG1-CG2_main"]
    for act in ("checkpoint", "mean", "sample"):
        _run_deploy(main, {"task": "CarGoal2"}, PaperPlan(act=act), [tmp_path] * 3, False)
    assert seen == [None, False, True]


def test_switch_deltas_and_direction_by_hand():
    # seed 0: costs 2 then 6 (delta +4); seed 1: 5 then 3 (delta -2); budget 4 -> VR deltas
    cost = [[2, 2, 6, 6], [5, 5, 3, 3]]
    d = T.switch_deltas(_run("x", 4.0, cost))
    np.testing.assert_allclose(d["cost"], [4.0, -2.0])
    np.testing.assert_allclose(d["vr"], [100.0, -100.0])


def test_table5_means_spearman_and_first_episodes_only():
    plan = PaperPlan(pairs=("CC1-CC2",), ctg_ratios=(0.2, 0.6, 1.0), episodes=2,
                     intervention_episodes=4)
    # episodes 3-4 (beyond plan.episodes) are 100 and must not count
    runs = [_run(f"fixed_ctg({r:g})", 30.0, [[c, c, 100, 100], [c + 2, c + 2, 100, 100]])
            for r, c in ((0.2, 1.0), (0.6, 5.0), (1.0, 3.0))]
    records = {"CC1-CC2_ctg": {"spec": {"name": "ctg"}, "results": {"runs": runs}}}
    _, data = T.table5(records, plan)
    assert data["CC1-CC2"]["means"] == {0.2: 2.0, 0.6: 6.0, 1.0: 4.0}
    assert data["CC1-CC2"]["stds"][0.2] == 1.0
    assert data["CC1-CC2"]["spearman"] == pytest.approx(0.5)


def test_claims_on_hand_made_numbers():
    plan = PaperPlan(pairs=("CG1-CG2", "PC1-PC2"), budgets=(25.0, 30.0, 40.0),
                     ablations=("safe_cdt", "zero_shot"), ctg_seeds=5)

    def s(vr, cost=5.0, ret=0.0, vr_std=1.0):
        return {"vr_mean": vr, "vr_std": vr_std, "mean_cost_mean": cost,
                "mean_return_mean": ret}

    data = {"t1": {"CG1-CG2": s(10.0, 8.0), "PC1-PC2": s(50.0, 20.0)},
            "t2": {25.0: s(30.0), 30.0: s(10.0), 40.0: s(12.0)},
            "t3": {"safe_cdt": s(10.0, vr_std=3.0), "zero_shot": s(12.0)},
            "t4": {"CG1-CG2": {"bcql": s(70.0, 26.0, 4.0), "bearl": s(90.0, 29.0, 7.0),
                               "cpq": s(20.0, 9.0, -0.5)}},
            "t5": {"CG1-CG2": {"spearman": 0.9, "means": {0.2: 5.0}},
                   "PC1-PC2": {"spearman": 0.4, "means": {0.2: 27.0, 1.0: 29.0}}},
            "t6": {("CG1-CG2", "low->high"): {"direction": 4, "seeds": 5},
                   ("CG1-CG2", "high->low"): {"direction": 3, "seeds": 5},
                   ("CG1-CG2", "fixed 0.2"): {"direction": None, "seeds": 5}},
            "per_seed_vr": {("PC1-PC2", "cpq"): [0.0, 100.0, 40.0]}}
    got = {c["claim"]: c["supported"] for c in claims(data, plan)}
    want = {
        "Safe-CDT's mean cost on CG1-CG2 is well below B (at most B/2)": True,
        "Safe-CDT has the lowest VR of Safe-CDT, BCQL, BEARL and CPQ on CG1-CG2": True,
        "VR depends on the pair (spread of at least 10 pp across pairs)": True,
        "VR at B = 25 exceeds VR at every B >= 30": True,
        "VR is non-monotone in B over B >= 30": False,  # 10 -> 12 only rises
        "All variants reach similar VR (spread within the largest seed std)": True,
        "Zero-shot VR lies within one seed std of Safe-CDT's": True,
        "BCQL and BEARL saturate the budget on CG1-CG2 (cost >= 0.8 B)": True,
        "CPQ is over-conservative on CG1-CG2 (cost <= B/2, reward <= 1)": True,
        "CPQ on PC1-PC2 is seed-unstable (per-seed VR spans >= 50 pp)": True,
        "Cost rises with the CTG ratio on every pair (Spearman > 0.5)": False,
        "CC1-CC2 shows the strongest cost response": None,  # CC not run
        "Every step change moves cost the expected way in >= 60% of its seeds (3 of 5), on every "
        "pair": True,
        "PC1-PC2's cost saturates near B (every ratio's cost >= 0.8 B)": True,
    }
    for claim, value in want.items():
        assert got[claim] is value, claim


# One budget and one variant in `studies` make it the same program as `main` (one compile
# fewer); the CTG sweep and the source sweep are one program each.
TINY = dict(pairs=("PC1-PC2",), study_pair="PC1-PC2", preset="tiny", horizon=10, episodes=10,
            intervention_episodes=10, budget=3.0, budgets=(3.0,), ablations=("safe_cdt",),
            ctg_ratios=(0.2, 1.0), main_seeds=2)


def test_cached_baselines_match_only_on_the_env_version_they_were_evaluated_on(tmp_path):
    from safecdt_jax.paper.run import _matching_baselines

    spec = {"pair": "CG1-CG2", "seeds": 3, "episodes": 20, "budget": 30.0, "preset": "cpu",
            "algos": ["cpq"], "data": "recipe-x", "env": envs.env_version("CarGoal2")}
    saved = {"pair": "CG1-CG2", "seeds": 3, "episodes": 20, "budget": 30.0, "preset": "cpu",
             "stop_over_budget": True, "methods": [{"algo": "cpq"}],
             "data": {"recipe": "recipe-x"}, "target_env": spec["env"]}
    path = tmp_path / "baselines.json"
    path.write_text(json.dumps(saved))
    assert _matching_baselines(tmp_path, spec) == saved
    for env in ("Car7-Goal2", None):  # evaluated on older rules, or before the check
        path.write_text(json.dumps({k: v for k, v in saved.items() if k != "target_env"}
                                   | ({"target_env": env} if env else {})))
        assert _matching_baselines(tmp_path, spec) is None


def test_run_paper_end_to_end_resume_and_cached_baselines(tiny_run, tmp_path, monkeypatch):
    from safecdt_jax.pretrain import default_pretrain, pretrain

    data, ckpt, _ = tiny_run
    monkeypatch.setenv("SAFECDT_CACHE", str(tmp_path / "cache"))
    # Tables 1-3 on two pretraining seeds' checkpoints x one deployment seed each.
    seed1 = pretrain(data, tmp_path / "seed1", preset="tiny", progress=False,
                     config=default_pretrain("tiny", steps=2, chunk=2, seed=1)).path
    ckpts = {"PC1-PC2": [ckpt, seed1]}
    plan = quick_plan(**TINY, baseline_algos=("cpq",), pretrain_seeds=2)
    # cached baselines with the plan's settings and the checkpoint's data: Table 7 uses them
    folder = baselines_folder("PC1-PC2", plan.baseline_preset)
    folder.mkdir(parents=True)
    costs = [[0.0] * 20, [10.0] * 20, [1.0] * 20]
    method = {"algo": "cpq", "returns": [[1.0] * 20] * 3, "costs": costs,
              "summary": {"mean_return_mean": 1.0, "mean_return_std": 0.0,
                          "mean_cost_mean": 11 / 3, "mean_cost_std": 4.5, "vr_mean": 100 / 3,
                          "vr_std": 47.1, "seeds": 3}}
    saved = {"pair": "PC1-PC2", "seeds": 3, "episodes": 20, "budget": 3.0, "preset": "cpu",
             "stop_over_budget": True, "methods": [method],
             "data": {"fingerprint": checkpoint_identity(ckpt)["data"]},
             "target_env": envs.env_version("PointCircle2")}
    (folder / "baselines.json").write_text(json.dumps(saved))
    out = tmp_path / "report"
    logs: list[str] = []
    summary = run_paper(plan, out, checkpoints=ckpts, progress=False, log=logs.append)
    assert set(summary["records"]) == {f"PC1-PC2_{n}" for n in
                                       ("main", "studies", "ctg", "source_ctg", "baselines")}
    report = (out / "REPORT.md").read_text()
    for heading in [f"## Table {i}" for i in range(1, 8)] + ["## Safety certificate",
                                                             "## Claims"]:
        assert heading in report, heading
    assert "| PC1→PC2 | CPQ |" in report and "Critical budget B* =" in report
    for fig in ("figure2.png", "PC1-PC2_scatter.png", "PC1-PC2/cost.png",
                "PC1-PC2/ctg_target.png"):
        assert (out / "figures" / fig).stat().st_size > 0, fig
    main = json.loads((out / "experiments" / "PC1-PC2_main.json").read_text())
    assert np.asarray(main["results"]["runs"][0]["metrics"]["cost"]).shape == (2, 10)
    assert [c["seed"] for c in main["spec"]["checkpoints"]] == [0, 1]
    assert main["results"]["deploy_seeds"] == 1 and "| PC1→PC2 |" in report
    assert "2 pretrained checkpoints x 1 deployment seed " in report and "| 2×1 |" in report
    ctg = json.loads((out / "experiments" / "PC1-PC2_ctg.json").read_text())
    assert [c["seed"] for c in ctg["spec"]["checkpoints"]] == [0, 1]  # Table 5 pools both
    assert np.asarray(ctg["results"]["runs"][0]["metrics"]["cost"]).shape == (2, 10)
    assert "CR 0.2 / CR 1" in report

    # a rerun reuses every finished experiment; a deleted one alone is redone
    (out / "experiments" / "PC1-PC2_ctg.json").unlink()
    stamp = (out / "experiments" / "PC1-PC2_studies.json").stat().st_mtime_ns
    logs.clear()
    again = run_paper(plan, out, checkpoints=ckpts, progress=False, log=logs.append)
    ran = [line.split(":")[0] for line in logs if line.endswith("running") or ": running" in line]
    assert ran == ["PC1-PC2_ctg"]
    assert (out / "experiments" / "PC1-PC2_studies.json").stat().st_mtime_ns == stamp
    assert again["records"]["PC1-PC2_main"] == summary["records"]["PC1-PC2_main"]
    # same key -> same bits: the redone experiment equals the first run's
    assert again["records"]["PC1-PC2_ctg"]["results"]["runs"] == \
        summary["records"]["PC1-PC2_ctg"]["results"]["runs"]


def test_quick_without_cached_baselines_skips_them(tiny_run, tmp_path, monkeypatch):
    _, ckpt, _ = tiny_run
    monkeypatch.setenv("SAFECDT_CACHE", str(tmp_path / "cache"))
    plan = quick_plan(**TINY)
    from safecdt_jax.paper.plan import Experiment
    from safecdt_jax.paper.run import run_experiment

    logs: list[str] = []
    e = Experiment("PC1-PC2", "baselines", "baselines", seeds=3, episodes=20)
    assert run_experiment(e, plan, ckpt, tmp_path, progress=False, log=logs.append) is None
    assert "skipped" in logs[-1] and not (tmp_path / "PC1-PC2_baselines.json").exists()


def test_prepare_seeds_trains_the_other_pretraining_seeds_beside_the_first(tiny_run, tmp_path,
                                                                          monkeypatch):
    from safecdt_jax.paper.run import prepare_seeds
    from safecdt_jax.pretrain import read_meta

    _, ckpt, _ = tiny_run
    monkeypatch.setenv("SAFECDT_CACHE", str(tmp_path))
    plan = quick_plan(**TINY, pretrain_seeds=3)
    got = prepare_seeds("PC1-PC2", plan, ckpt, progress=False)
    assert got[0] == ckpt and [p.name for p in got[1:]] == ["PointCircle1-tiny-seed1",
                                                             "PointCircle1-tiny-seed2"]
    first = read_meta(ckpt)
    for k, path in enumerate(got[1:], start=1):
        meta = read_meta(path)
        assert meta["pretrain"] == {**first["pretrain"], "seed": k}
        assert meta["model"] == first["model"] and meta["step"] == first["step"]
    stamp = (got[1] / str(first["step"])).stat().st_mtime_ns
    assert prepare_seeds("PC1-PC2", plan, ckpt, progress=False) == got  # reused as they are
    assert (got[1] / str(first["step"])).stat().st_mtime_ns == stamp
    assert prepare_seeds("PC1-PC2", quick_plan(**TINY), ckpt) == [ckpt]


def _collected(path, observations_shift=0.0, seed=0):
    """The tiny expert episodes written as a seeded collection would write them (the attributes
    `experts.collect.recipe_fields` reads), observations shifted by `observations_shift` (the
    same recipe with other bits, as another kind of CPU collects it)."""
    import dataclasses

    from data_helpers import expert_episodes

    from safecdt_jax.data.collect import write_collected
    from safecdt_jax.data.dataset import Attrs

    data = expert_episodes()
    attrs = dict(data.attrs) | {"seed": seed, "grid_filter": {"max_cost": 120.0, "target": 4}}
    data = dataclasses.replace(data, observations=data.observations + observations_shift,
                               attrs=Attrs(attrs))
    return write_collected(path, data)


def test_identity_names_the_data_recipe_and_upgrades_records_keyed_on_the_same_bits(
        tiny_run, tmp_path):
    from safecdt_jax.paper.run import experiment_spec, load_record, run_experiment, seeded_identity
    from safecdt_jax.pretrain import default_pretrain, pretrain

    cfg = default_pretrain("tiny", steps=2, chunk=2)
    here, there = (pretrain(_collected(tmp_path / f"{name}.hdf5", shift), tmp_path / name,
                            preset="tiny", config=cfg, progress=False).path
                   for name, shift in (("here", 0.0), ("there", 1e-3)))
    # Same recipe, other bits: the same identity, which the bit-level (legacy) one tells apart.
    assert checkpoint_identity(here) == checkpoint_identity(there)
    assert checkpoint_identity(here)["data"].startswith("recipe-")
    assert checkpoint_identity(here, legacy=True)["data"] != \
        checkpoint_identity(there, legacy=True)["data"]
    assert checkpoint_identity(here, recipe="recipe-other") != checkpoint_identity(here)
    # Data without a recipe (a raw rollout: no seed) keep the bit-level identity.
    _, plain, _ = tiny_run
    assert checkpoint_identity(plain) == checkpoint_identity(plain, legacy=True)

    # A record keyed on these checkpoints' bits is reused and its spec rewritten; one keyed on
    # other bits is not.
    plan = quick_plan(**TINY)
    e = next(x for x in experiments(plan) if x.key == "PC1-PC2_main")
    folder = tmp_path / "experiments"
    folder.mkdir()
    legacy = {"spec": experiment_spec(e, plan, seeded_identity([here], legacy=True)),
              "seconds": 5.0, "finished": "2026-12-07 03:00:00", "results": {"made": "here"}}
    (folder / f"{e.key}.json").write_text(json.dumps(legacy))
    logs: list[str] = []
    record = run_experiment(e, plan, [here], folder, progress=False, log=logs.append)
    current = json.loads(json.dumps(experiment_spec(e, plan, seeded_identity([here]))))
    assert record["results"] == {"made": "here"} and record["spec"] == current
    assert record["data_fingerprint"] == checkpoint_identity(here, legacy=True)["data"]
    assert json.loads((folder / f"{e.key}.json").read_text())["spec"] == current
    assert any("now names the data's recipe" in line for line in logs)
    assert load_record(folder / f"{e.key}.json", current) is not None
    other = experiment_spec(e, plan, seeded_identity([there], legacy=True))
    (folder / "other.json").write_text(json.dumps(dict(legacy, spec=other)))
    assert load_record(folder / "other.json",
                       experiment_spec(e, plan, seeded_identity([here], legacy=True))) is None
