"""``compile=true`` (nrt/compile.py, nrt.callbacks.CompileHotCode): the compiled hot code
computes what the eager code computes, and a machine without a compiler trains eagerly."""

from __future__ import annotations

import logging

import lightning as L
import pytest
import torch

from nrt.callbacks import CompileHotCode
from nrt.compile import missing_compiler, use_cache
from nrt.data.datamodule import RayDataModule
from nrt.modules.fields.ea_field import EAField
from nrt.stages.ea import EAModule

pytestmark = pytest.mark.integration

HAVE_CXX = missing_compiler("cpu") is None


@pytest.fixture
def no_cache_choice(monkeypatch):
    """``TORCHINDUCTOR_CACHE_DIR`` unset for the test and restored after it (setenv records
    the original state, so what the test's code sets is undone too)."""
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", "")
    monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR")


def test_no_compiler_on_the_path_is_named_with_the_fix(monkeypatch, tmp_path):
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.delenv("CXX", raising=False)
    assert "no C++ compiler found (g++, c++, clang++; set CXX" in missing_compiler("cpu")
    monkeypatch.setenv("CXX", "my-c++")
    assert "(my-c++;" in missing_compiler("cpu")


def test_the_kernel_cache_goes_where_asked_unless_the_user_chose(no_cache_choice, tmp_path):
    use_cache(str(tmp_path / "cache"))
    assert (tmp_path / "cache").is_dir()
    import os

    assert os.environ["TORCHINDUCTOR_CACHE_DIR"] == str(tmp_path / "cache")
    use_cache(str(tmp_path / "other"))  # the first choice (or the user's) stays
    assert os.environ["TORCHINDUCTOR_CACHE_DIR"] == str(tmp_path / "cache")


def test_commands_build_extensions_in_their_output_folder_unless_the_user_chose(
        monkeypatch, tmp_path):
    """nrt's commands point the C++ extensions' build folder into the output folder
    (beside inductor's kernels); a folder the user set stays."""
    import os

    from nrt.cli.common import keep_extensions_in
    from nrt.compile import EXTENSIONS_DIR_ENV, extensions_dir

    monkeypatch.setenv(EXTENSIONS_DIR_ENV, "")
    monkeypatch.delenv(EXTENSIONS_DIR_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "home_cache"))
    assert extensions_dir() == tmp_path / "home_cache" / "nrt" / "extensions"
    keep_extensions_in(str(tmp_path / "out"))
    assert extensions_dir() == tmp_path / "out" / ".cache" / "extensions"
    keep_extensions_in(str(tmp_path / "other"))  # the first choice (or the user's) stays
    assert os.environ[EXTENSIONS_DIR_ENV] == str(tmp_path / "out" / ".cache" / "extensions")


def test_without_a_compiler_the_run_trains_eagerly_and_says_so(monkeypatch, tmp_path, caplog,
                                                              tiny_dataset):
    model = EAModule(density_field={"_target_": "nrt.modules.fields.ea_field.EAField",
                                    "_partial_": True, "hidden": 16,
                                    "hash_grid": {"levels": 4, "log2_table_size": 12}},
                     samples_per_ray=16)
    dm = RayDataModule(str(tiny_dataset), batch_size=128, steps_per_epoch=2, val_views=1)
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.delenv("CXX", raising=False)
    callback = CompileHotCode(enabled=True, cache_dir=str(tmp_path / "cache"))
    trainer = L.Trainer(max_steps=2, accelerator="cpu", logger=False,
                        enable_checkpointing=False, enable_progress_bar=False,
                        num_sanity_val_steps=0, limit_val_batches=0, inference_mode=False,
                        callbacks=[callback])
    with caplog.at_level(logging.WARNING, logger="nrt.callbacks"):
        trainer.fit(model, datamodule=dm)
    assert not callback.compiled and trainer.global_step == 2
    assert model.field._compiled_call_impl is None  # nn.Module.compile was not called
    assert "no C++ compiler found" in caplog.text and "eager code" in caplog.text
    assert float(trainer.callback_metrics["time/first_step_s"]) > 0


@pytest.mark.skipif(not HAVE_CXX, reason="no C++ compiler for inductor here")
def test_with_a_compiler_the_stage_compiles_its_field_and_caches_where_asked(no_cache_choice,
                                                                             tmp_path):
    """The callback's setup compiles in place (compilation itself waits for the first call,
    so nothing is built here) and points inductor's cache at ``cache_dir``."""
    model = EAModule(density_field={"_target_": "nrt.modules.fields.ea_field.EAField",
                                    "_partial_": True, "hidden": 16,
                                    "hash_grid": {"levels": 4, "log2_table_size": 12}})
    callback = CompileHotCode(enabled=True, cache_dir=str(tmp_path / "cache"))
    callback.setup(L.Trainer(accelerator="cpu", logger=False), model, "fit")
    assert callback.compiled and model.field._compiled_call_impl is not None
    assert (tmp_path / "cache").is_dir()
    keys = set(model.state_dict())
    assert keys and not any("_orig_mod" in k for k in keys)  # checkpoints keep their keys


def small_field() -> EAField:
    return EAField(hash_grid={"levels": 4, "log2_table_size": 12, "base_resolution": 4},
                   hidden=16)


@pytest.mark.slow
@pytest.mark.skipif(not HAVE_CXX, reason="no C++ compiler for inductor here")
def test_a_compiled_field_gives_the_eager_density_colour_and_gradients():
    """Fused float32 ops reorder sums: values and gradients agree to a few ulps of float32
    relative to their scale (rtol 1e-5), not bit for bit."""
    torch.manual_seed(0)
    eager, compiled = small_field(), small_field()
    compiled.load_state_dict(eager.state_dict())
    compiled.compile(dynamic=True)
    for n in (300, 257):  # two ray counts: one compiled graph serves both
        x, d = torch.rand(n, 3) * 2 - 1, torch.nn.functional.normalize(torch.randn(n, 3), dim=-1)
        outs = []
        for field in (eager, compiled):
            field.zero_grad()
            sigma, rgb = field(x, d)
            (sigma.square().sum() + rgb.sum()).backward()
            outs.append((sigma.detach(), rgb.detach(),
                         [p.grad.clone() for p in field.parameters()]))
        for a, b in zip(outs[0][:2], outs[1][:2], strict=True):
            torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-6 * float(a.abs().max()))
        for ga, gb in zip(outs[0][2], outs[1][2], strict=True):
            torch.testing.assert_close(gb, ga, rtol=1e-4, atol=1e-5 * float(ga.abs().max()))
