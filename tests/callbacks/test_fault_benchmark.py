"""The fault-benchmark callback through the real CLI: TensorBoard scalars and figure during fit, files at test."""
import json
import math
import os

import numpy as np
import pytest

from lightning_bodyschema.cli import main as cli_main

COMMON = ["--model=DiffusionSchema", "--data.n_samples=200", "--model.n_timesteps=50", "--faults.n_per_condition=4",
          "--faults.binding_n_per_condition=3"]


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """60 epochs of a small DiffusionSchema, benchmarked after epochs 30 and 60 (earlier its motor lengths are
    metres off and every command is out_of_range); (checkpoint, log folder, tmp)."""
    tmp = tmp_path_factory.mktemp("faults")
    root = str(tmp / "run")
    cli_main(["fit", *COMMON, "--trainer.max_epochs=60", "--trainer.check_val_every_n_epoch=10",
              "--faults.every_n_epochs=30", f"--trainer.default_root_dir={root}", f"--data.cache_dir={tmp / 'cache'}"])
    logdir = os.path.join(root, "lightning_logs", "version_0")
    ckpts = sorted(os.listdir(os.path.join(logdir, "checkpoints")))
    assert ckpts, "fit wrote no checkpoint"
    return os.path.join(logdir, "checkpoints", ckpts[-1]), logdir, tmp


def test_fit_logs_fault_scalars_and_boxplots(fitted):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    _, logdir, _ = fitted
    events = EventAccumulator(logdir, size_guidance={"images": 0, "scalars": 0})
    events.Reload()
    scalars = set(events.Tags()["scalars"])
    always = ["fault/adapt_ok_fraction", "fault/adapt_seconds", "fault/evaluate_seconds"]
    for reading in ("paper", "phys"):
        always += [f"fault/{reading}/CUT/E_cut_all", f"fault/{reading}/FIX/E_fix_mm_all",
                   f"fault/{reading}/BOTH/E_cut_all", f"fault/{reading}/BOTH/E_fix_mm_all",
                   f"fault_unadapted/{reading}/CUT/E_cut_all"]
        always += [f"fault/{reading}/{c}/{m}_all" for c in ("CUT", "FIX", "BOTH") for m in ("E_tau", "E_q", "E_q_phys")]
        always += [f"fault/{reading}/{c}/n_feasible" for c in ("CUT", "FIX", "BOTH")]
        always += [f"fault/{reading}/{c}/n_unsettled_all" for c in ("CUT", "FIX", "BOTH")]  # apart from E_q_phys
    for tag in always:
        assert tag in scalars, f"{tag} missing from {sorted(t for t in scalars if t.startswith('fault'))}"
        values = events.Scalars(tag)
        # at the validation steps of epochs 30 and 60 (160 train samples in batches of 64: 3 optimizer steps an epoch)
        assert [v.step for v in values] == [89, 179], f"{tag} logged at steps {[v.step for v in values]}"
        assert all(math.isfinite(v.value) for v in values), tag
    # undefined metrics are not logged as numbers: nothing is jammed under CUT, nothing ruptured under FIX
    assert not any(t.startswith(("fault/phys/CUT/E_fix", "fault/phys/FIX/E_cut")) for t in scalars)
    assert events.Scalars("fault/adapt_ok_fraction")[-1].value == 1.0
    assert "fault/boxplots" in events.Tags()["images"]
    image = events.Images("fault/boxplots")
    assert [i.step for i in image] == [89, 179] and image[-1].width > 300 and image[-1].height > 300


def test_test_writes_identical_json_and_a_markdown_table(fitted, capsys):
    ckpt, _, tmp = fitted
    texts = {"paper": [], "binding": []}
    for i in range(2):
        out = tmp / f"test{i}"
        cli_main(["test", *COMMON, f"--ckpt_path={ckpt}", f"--faults.out_dir={out}",
                  f"--trainer.default_root_dir={tmp / 'run'}", f"--data.cache_dir={tmp / 'cache'}"])
        printed = capsys.readouterr().out
        for protocol, suffix, conds in (("paper", "", ("CUT", "FIX", "BOTH")),
                                        ("binding", "_binding", ("CUT", "FIX", "BOTH", "WEAK", "BAND"))):
            json_path, md_path = out / f"fault_benchmark{suffix}.json", out / f"fault_benchmark{suffix}.md"
            assert json_path.is_file() and md_path.is_file()
            assert str(json_path) in printed and f"{protocol} protocol" in printed
            texts[protocol].append(json_path.read_bytes())
            table = md_path.read_text()
            assert "| condition | reading | subset | command | n | E_cut [N] | E_fix [mm] | E_tau [N m] |" in table
            for cond in conds:  # 2 readings x 2 subsets x (adapted, unadapted, oracle)
                assert table.count(f"| {cond} |") == 12, cond
                assert f"| {cond} | phys | feasible | oracle |" in printed  # the printed table has the oracle row
            assert "ms per case" in table
    for protocol, (first, second) in texts.items():
        assert first == second, f"reruns must give byte-identical JSON ({protocol})"
    report = json.loads(texts["paper"][0])
    assert not list(tmp.glob("test*/.tmp-*")), "temporary files left behind"
    for kind in ("adapted", "unadapted", "oracle"):
        for reading in ("paper", "phys"):
            by_cond = report["summary"][kind][reading]
            assert set(by_cond) == {"CUT", "FIX", "BOTH"}
            for cond in ("CUT", "FIX", "BOTH"):
                assert by_cond[cond]["all"]["n"] == 4
                # settle runs never at rest are counted, and E_q_phys's median is over the others only
                unsettled = np.array(report["per_case"][kind][reading]["settle_unsettled"], bool)
                rows = np.array(report["cases"]["cond"]) == cond
                assert by_cond[cond]["all"]["n_unsettled"] == int(unsettled[rows].sum())
                e_q_phys = report["per_case"][kind][reading]["E_q_phys"]
                assert all(e_q_phys[i] is None for i in np.flatnonzero(unsettled))
            assert by_cond["CUT"]["all"]["E_fix"] is None and by_cond["FIX"]["all"]["E_cut"] is None
    for kind in ("adapted", "unadapted"):
        for cond in ("CUT", "FIX", "BOTH"):
            assert report["summary"][kind]["phys"][cond]["all"]["E_tau"] is not None
    assert len(report["cases"]["cond"]) == 12 and len(report["per_case"]["adapted"]["phys"]["E_tau"]) == 12
    assert np.array(report["cases"]["q_ref"]).shape == (12, 2)
    assert report["adapt_status"] == ["ok"] * 12
    binding = json.loads(texts["binding"][0])
    assert binding["meta"]["protocol"] == "binding" and len(binding["cases"]["cond"]) == 15
    for name, report in (("paper", report), ("binding", binding)):
        for reading in ("paper", "phys"):
            feasible = np.array(binding["feasible"][reading] if name == "binding" else report["feasible"][reading])
            assert name == "paper" or reading == "paper" or feasible.all()  # binding: every case, physically
            oracle = report["per_case"]["oracle"][reading]
            for metric in ("E_cut", "E_fix", "E_weak", "E_band", "E_tau", "E_q"):
                values = np.array([np.nan if v is None else v for v in oracle[metric]], float)[feasible]
                assert np.nanmax(values, initial=0.0) <= 1e-6, (name, reading, metric)


def test_boxplots_grid_has_na_panels(fitted, tmp_path):
    """The figure function alone: 4 x 3 panels, one box per model, E_fix under CUT says n/a."""
    from lightning_bodyschema.callbacks.fault_benchmark import FaultBenchmark
    from lightning_bodyschema.evaluation import make_fault_cases, run_fault_benchmark
    from lightning_bodyschema.plots.arm import save_figure_atomic
    from lightning_bodyschema.plots.boxplots import fault_boxplots
    from lightning_bodyschema.schemas import load_schema

    from lightning_bodyschema.schemas import load_datamodule

    schema = load_schema(fitted[0])
    q, x = (t.numpy() for t in load_datamodule(fitted[0]).splits["val"])
    cases = make_fault_cases(q, x[:, :schema.n_muscles], 3, seed=0)  # l_fixed: real motor lengths
    result = run_fault_benchmark(schema.robot_model, schema.spring, cases, schema.infer, schema.adapt)
    fig = fault_boxplots({"Diff": result, "Diff again": result}, reading="paper", subset="all")
    axes = fig.get_axes()
    assert len(axes) == 12
    texts = {(i // 3, i % 3): [t.get_text() for t in ax.texts] for i, ax in enumerate(axes)}
    assert texts[(1, 0)] == ["n/a"] and texts[(0, 1)] == ["n/a"]  # E_fix under CUT, E_cut under FIX
    assert texts[(2, 2)] == []
    save_figure_atomic(fig, tmp_path / "boxes.png")
    assert (tmp_path / "boxes.png").stat().st_size > 10_000
    with pytest.raises(Exception, match="reading"):
        fault_boxplots({"Diff": result}, reading="nope")
    with pytest.raises(Exception, match="variant"):
        FaultBenchmark(variant="nope")
