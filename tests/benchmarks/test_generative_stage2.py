"""benchmarks/generative_stage2.py: a run's rows hold every member's first and last
validation, read alike from the CSV log and from TensorBoard; stage-1 runs are found by
what they train; the summary counts the members below their start; a killed run's folder
is refused, exit status 2, before anything is read or trained."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import yaml
from omegaconf import OmegaConf
from torch.utils.tensorboard import SummaryWriter

from benchmarks.common import compose_train, read_table
from benchmarks.generative_stage2 import (
    CONFIGS,
    FIELDS,
    PROPERTIES,
    append_rows,
    run_rows,
    stage1_checkpoint,
    summary,
)
from tests.benchmarks.test_generative_stage1 import write_log

pytestmark = pytest.mark.unit

K = 3


def validation(step: int, scale: float) -> dict[str, float]:
    """A validation record: member k's property MSE ``scale * (k + 1) * (i + 1)``."""
    record = {"step": step, "val/mse_sigma_t_x100": scale}
    for k in range(K):
        record[f"val/psnr_member{k}"] = 30.0 + k
        for i, prop in enumerate(PROPERTIES):
            record[f"val/mse_{prop}_x100_member{k}"] = scale * (k + 1) * (i + 1)
    return record


def write_run_json(run, steps: int = 20) -> None:
    run.mkdir(parents=True, exist_ok=True)
    (run / "run.json").write_text(json.dumps({
        "members": [f"family_seed{k}" for k in range(K)], "finished_step": steps,
        "final_metrics": {"time/wall_s": 12.34}}))


def expected_rows() -> list[tuple[str, str, str]]:
    """(member, sigma_t start, sigma_t end) of a log going from scale 10 to scale 4."""
    return [(str(k), f"{10.0 * (k + 1):.4f}", f"{4.0 * (k + 1):.4f}") for k in range(K)]


def test_the_rows_of_a_csv_logged_run_are_its_first_and_last_validation(tmp_path) -> None:
    write_log(tmp_path, [validation(0, 10.0), {"step": 5, "train/loss": 0.2},
                         validation(9, 7.0), validation(19, 4.0)])
    write_run_json(tmp_path)
    rows = run_rows(tmp_path, "default", "default", "cpu", 1)
    assert [(str(r["member"]), r["sigma_t_start"], r["sigma_t_end"]) for r in rows] \
        == expected_rows()
    assert rows[2]["g_start"] == f"{10.0 * 3 * 4:.4f}" and rows[2]["psnr_end"] == "32.000"
    assert rows[0]["train_s"] == "12.3" and rows[0]["steps"] == 20


def test_a_run_logged_only_to_tensorboard_gives_the_same_rows(tmp_path) -> None:
    writer = SummaryWriter(str(tmp_path / "tensorboard"))
    for record in (validation(0, 10.0), validation(9, 7.0), validation(19, 4.0)):
        for key, value in record.items():
            if key != "step":
                writer.add_scalar(key, value, record["step"])
    writer.add_scalar("train/loss", 0.3, 25)  # a training scalar after the last validation
    writer.close()
    write_run_json(tmp_path)
    rows = run_rows(tmp_path, "default", "default", "cpu", 0)
    assert [(str(r["member"]), r["sigma_t_start"], r["sigma_t_end"]) for r in rows] \
        == expected_rows()


def test_a_stage1_run_is_found_by_what_it_trains(tmp_path, monkeypatch) -> None:
    """The default stage 1 is found under other spellings of the same config (the preset's
    steps doubled by hand, the input named), and not in runs of another seed or input."""
    monkeypatch.setenv("NRT_OUTPUT_DIR", str(tmp_path))
    base = ["stage=ea", "preset=cpu", f"paths.data_dir={tmp_path / 'datasets'}",
            "scene=family", "mode=generative"]
    spelled = ["mode.latent.input=true", "mode.latent.ea_steps_scale=1",
               "budget.ea.steps=3000", "seed=1"]
    for name, overrides in (("a_same", spelled), ("b_other_seed", [*spelled[:-1], "seed=0"]),
                            ("c_no_input", ["mode.latent.input=false", "seed=1"])):
        run = tmp_path / "family" / "ea" / name
        (run / ".hydra").mkdir(parents=True)
        OmegaConf.save(compose_train([*base, *overrides]), run / ".hydra" / "config.yaml")
        (run / "checkpoints").mkdir()
        (run / "checkpoints" / "last.ckpt").write_bytes(b"")
        write_run_json(run)
    found = stage1_checkpoint("default", "cpu", 1)
    assert found == (tmp_path / "family" / "ea" / "a_same" / "checkpoints" / "last.ckpt")


def test_the_summary_counts_the_members_below_their_start(tmp_path) -> None:
    table = tmp_path / "rows.csv"
    base = {"stage1": "default", "config": "default", "preset": "cpu", "seed": 0,
            "psnr_end": 30, "train_s": "100.0", "steps": 10, "overrides": ""}
    ends = (5.0, 12.0, 30.0)  # members 1 and 2 end above their start of 10
    append_rows(table, FIELDS, [{**base, "member": k, "sigma_t_start": 10.0,
                         "sigma_t_end": ends[k], "sigma_s_start": 8.0, "sigma_s_end": 4.0,
                         "sigma_a_start": 1, "sigma_a_end": 1, "g_start": 1, "g_end": 1}
                        for k in range(K)])
    line = summary(read_table(table)).splitlines()[2]
    assert line == ("| default | default | cpu | 0 | 10.0 -> 15.7 | 8.0 -> 4.0 "
                    "| 1 / 3 | 3.00 | 100.0 |")


@pytest.mark.parametrize("module", ["generative_stage2", "generative_samples"])
def test_a_killed_run_given_as_from_run_is_refused(tmp_path, module) -> None:
    """Both benchmarks that read a finished run refuse a killed one (run.json without
    finished_step) with the resume command's key, and leave their table unwritten."""
    (tmp_path / "run.json").write_text(json.dumps({"members": ["family_seed0"]}))
    table = tmp_path / "table.csv"
    config = ["--configs" if module == "generative_stage2" else "--config",
              "two_a_step_dim16_free_offsets"]
    proc = subprocess.run([sys.executable, "-m", f"benchmarks.{module}", "--from-run",
                           str(tmp_path), *config, "--seeds", "1", "--table", str(table)],
                          capture_output=True, text=True)
    assert proc.returncode == 2, proc.stderr
    assert "did not reach its end" in proc.stderr and "resume=" in proc.stderr
    assert not table.exists()


@pytest.mark.parametrize("config", sorted(CONFIGS))
def test_every_configuration_composes_with_its_overrides_in_place(config):
    """Each measured configuration composes as the benchmark trains it, and every override
    holds its value in the composed config (a key the preset or the mode set again would
    measure something else under the configuration's name)."""
    cfg = compose_train(["stage=rte", "preset=cpu", "scene=family", "mode=generative",
                         *CONFIGS[config]])
    for override in CONFIGS[config]:
        key, value = override.split("=", 1)
        assert OmegaConf.select(cfg, key) == yaml.safe_load(value), override
