"""tools/diagnose.py, tools/predict.py --faults and tools/fault_drill.py on a small structured checkpoint of the
paper arm: diagnose then adapt in two commands, one-line refusals that write nothing, and a drill that finds a cut."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from physics_checks import fit_structured

from lightning_bodyschema.apps.diagnose import diagnose_main
from lightning_bodyschema.apps.fault_drill import fault_drill_main
from lightning_bodyschema.apps.predict import predict_main
from lightning_bodyschema.data import EquilibriumDataModule
from lightning_bodyschema.diagnosis import SensorLog, SensorNoise, write_sensor_log
from lightning_bodyschema.diagnosis.sensors import noisy, true_readings
from lightning_bodyschema.faults import Faults


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    dm = EquilibriumDataModule(n_samples=1000, seed=0, cache_dir=None)
    schema, trainer = fit_structured(dm, length_model="per_muscle", path_degree=10, torque_model="gravity")
    path = str(tmp_path_factory.mktemp("ckpt") / "structured.ckpt")
    trainer.save_checkpoint(path, weights_only=False)
    return path, schema, dm


def _cut_log(schema, dm, path, muscle="elbow_flexor"):
    arm, spring = schema.robot_model, schema.spring
    q = dm.splits["val"][0].numpy()[:3]
    l_cmd, f_cmd = schema.infer(q)
    faults = Faults.from_names(arm.muscle_names, cut=[[muscle]] * 3)
    read = noisy(true_readings(arm, spring, q, l_cmd, f_cmd, faults), spring, SensorNoise(), np.random.default_rng(0))
    write_sensor_log(path, SensorLog.from_rows(arm.joint_names, arm.muscle_names, read[0], read[1], l_cmd, f_cmd,
                                               read[2], case=np.full(3, 4)))


def test_diagnose_then_adapt_in_two_commands(checkpoint, tmp_path):
    ckpt, schema, dm = checkpoint
    log, out = str(tmp_path / "log.csv"), str(tmp_path / "diagnosis.json")
    _cut_log(schema, dm, log)
    diagnose_main(["--ckpt", ckpt, "--log", log, "--out", out])
    [entry] = json.load(open(out))
    assert entry["case"] == 4 and entry["status"] == "identified" and entry["faults"] == {"cut": ["elbow_flexor"]}
    assert entry["muscles"]["elbow_flexor"]["kind"] == "cut" and entry["muscles"]["elbow_flexor"]["score"] > 16
    requests, commands = tmp_path / "requests.yaml", str(tmp_path / "commands.json")
    requests.write_text("- q_ref: [0.3, -0.2]\n")
    predict_main(["--ckpt", ckpt, "--requests", str(requests), "--faults", out, "--out", commands])
    [result] = json.load(open(commands))["results"]
    m = schema.robot_model.muscle_names.index("elbow_flexor")
    assert result["status"] == "ok" and result["cut"][m] is True and result["f"][m] == 0.0


@pytest.mark.parametrize("edit, message", [
    (lambda text: text.replace(",l_cmd_elbow_flexor", ",l_cmd_elbow_flexr"), "did you mean 'l_cmd_elbow_flexor'"),
    (lambda text: text.replace("\n4,", "\n4,nan,", 1).replace(",nan,", ",nan,", 1), None),
    (lambda text: text.replace("# units: SI", "# units: mm"), "units flag 'mm'"),
])
def test_bad_logs_are_refused_in_one_line_and_nothing_is_written(checkpoint, tmp_path, capsys, edit, message):
    ckpt, schema, dm = checkpoint
    log, out = tmp_path / "log.csv", tmp_path / "diagnosis.json"
    _cut_log(schema, dm, str(log))
    text = log.read_text()
    lines = text.splitlines()
    if message is None:  # a NaN reading in the second data row
        cells = lines[3].split(",")
        cells[2] = "nan"
        lines[3] = ",".join(cells)
        text, message = "\n".join(lines) + "\n", "is NaN/inf in row 2"
    else:
        text = edit(text)
    log.write_text(text)
    with pytest.raises(SystemExit) as exit_:
        diagnose_main(["--ckpt", ckpt, "--log", str(log), "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_.value.code == 2 and len(err) == 1 and message in err[0]
    assert not out.exists()


def test_a_drill_finds_a_cut_and_adapts_as_well_as_the_true_faults(checkpoint, tmp_path):
    ckpt, _, _ = checkpoint
    out = tmp_path / "drill"
    fault_drill_main(["--ckpt", ckpt, "--fault", "cut:elbow_flexor", "--seconds", "1.6", "--at", "0.8",
                      "--out", str(out)])
    summary = json.load(open(out / "summary.json"))
    assert summary["identified"] == {"elbow_flexor": "cut"} and summary["adapted_status"] == "ok"
    assert 0 < summary["detection_delay_s"] <= 0.1  # window 5 + confirm 3 ticks of 10 ms
    rest = summary["rest_error_rad"]
    assert rest["diagnosed"] <= 1.1 * rest["true_faults"] + 1e-4 and rest["diagnosed"] < 0.2 * rest["healthy"]
    assert os.path.getsize(out / "drill.png") > 10_000
    with pytest.raises(SystemExit):
        fault_drill_main(["--ckpt", ckpt, "--fault", "jam:elbow_flexor", "--out", str(tmp_path / "bad")])
