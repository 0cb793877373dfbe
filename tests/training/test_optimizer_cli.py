"""--optimizer / --lr_scheduler as LightningCLI documents them; the schema's Adam + cosine schedule by default."""
import warnings

import pytest
import torch

from lightning_bodyschema.cli import main as cli_main


def fit(tmp_path, *args):
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*LightningCLI's args parameter.*")
        return cli_main(["fit", "--model=VAESchema", "--trainer.max_epochs=3", "--trainer.logger=false",
                         "--progress.enabled=false",
                         "--faults.every_n_epochs=0", f"--trainer.default_root_dir={tmp_path}",
                         f"--data.cache_dir={tmp_path / 'cache'}", *args])


def test_default_is_fused_adam_with_the_cosine_schedule_to_lr_final(tmp_path):
    cli = fit(tmp_path, "--model.lr=0.002", "--model.lr_final=1e-4")
    optimizer = cli.trainer.optimizers[0]
    assert type(optimizer) is torch.optim.Adam and optimizer.defaults["fused"]
    (config,) = cli.trainer.lr_scheduler_configs
    assert isinstance(config.scheduler, torch.optim.lr_scheduler.CosineAnnealingLR) and config.interval == "epoch"
    assert config.scheduler.T_max == 3 and config.scheduler.eta_min == 1e-4
    assert optimizer.param_groups[0]["initial_lr"] == 0.002
    assert optimizer.param_groups[0]["lr"] == pytest.approx(1e-4)  # annealed to lr_final at the last epoch


def test_optimizer_and_lr_scheduler_from_the_command_line(tmp_path):
    cli = fit(tmp_path, "--optimizer", "AdamW", "--optimizer.lr", "3e-4", "--optimizer.weight_decay", "0.01",
              "--lr_scheduler", "CosineAnnealingLR", "--lr_scheduler.T_max", "3")
    optimizer = cli.trainer.optimizers[0]
    assert type(optimizer) is torch.optim.AdamW
    assert optimizer.param_groups[0]["initial_lr"] == 3e-4 and optimizer.param_groups[0]["weight_decay"] == 0.01
    (config,) = cli.trainer.lr_scheduler_configs
    assert isinstance(config.scheduler, torch.optim.lr_scheduler.CosineAnnealingLR) and config.scheduler.T_max == 3
    assert cli.trainer.global_step == 30 and int(next(iter(optimizer.state.values()))["step"]) == 30


def test_lr_scheduler_without_optimizer_exits_2(tmp_path, capsys):
    # in process (the console script's own exit path is tests/cli/test_cli_usability.py's)
    with pytest.raises(SystemExit) as stop:
        fit(tmp_path, "--trainer.max_epochs=1", "--lr_scheduler", "StepLR", "--lr_scheduler.step_size", "1")
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "--lr_scheduler" in err and "--optimizer" in err
    assert "Traceback" not in err


def test_optimizer_and_lr_scheduler_from_a_yaml_config(tmp_path):
    config = tmp_path / "opt.yaml"
    config.write_text("optimizer:\n  class_path: torch.optim.AdamW\n  init_args:\n    lr: 0.0003\n"
                      "lr_scheduler:\n  class_path: torch.optim.lr_scheduler.StepLR\n  init_args:\n    step_size: 1\n"
                      "    gamma: 0.5\n")
    cli = fit(tmp_path, f"--config={config}")
    optimizer = cli.trainer.optimizers[0]
    assert type(optimizer) is torch.optim.AdamW and optimizer.param_groups[0]["initial_lr"] == 3e-4
    assert optimizer.param_groups[0]["lr"] == pytest.approx(3e-4 * 0.5 ** 3)  # halved after each of 3 epochs
