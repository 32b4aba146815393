"""Where a training step's time goes, and how close it is to the machine.

    python -m benchmarks.profile_step [--stage ea|rte|dpt] [--preset cpu] [--steps 20]
        [--warmup 5] [--at 0.5] [--scene default] [--ea-ckpt PATH] [--probe-seconds 1]
        [--json PATH] [override ...]

**The run.** The real training: the ``nrt-train`` config composed as the CLI composes it
(:func:`benchmarks.common.compose_train`; trailing Hydra overrides are passed on), the model,
datamodule, callbacks and loggers instantiated from it as ``nrt.cli.train`` does (the
checkpointers left out, the loggers writing into a temporary folder, validation and the
progress bar off), trained by a real Lightning Trainer for ``warmup + 2 * steps`` steps: the
warm-up, ``steps`` timed without the profiler, then ``steps`` under ``torch.profiler``
(CPU activity, ``record_shapes``, ``with_flops``). Stages 2 and dpt start from the scene's
newest EA checkpoint on the preset's photos (``--ea-ckpt`` names one; without any, one is
trained). The run's progress, which the stages' schedules read (the photo objective's
warm-up, the medium's coarse-to-fine grid, the learning rate), is pinned at ``--at`` (0.5:
mid-run) by a run clock (:class:`~nrt.stages.schedules.RunClock`), so that a few steps
profile the step of a run in progress, not of its first steps; ``--at 0`` leaves the
schedules to the steps. Step wall times come from a plain timer at the end of each batch
(``time.perf_counter``), never from the profiler; both windows are reported, so the
profiler's own overhead is visible. Stage 2 refreshes its uncollided light every
``uncollided_every`` steps (10): give ``--steps`` a multiple of it for the refresh's
average share (the count in the profiled window is printed).

**Attribution, exact.** Every microsecond of the profiled window on the training thread goes
to exactly one component, so the rows sum to the window's wall time (100 %):

- Scopes: nrt's ``record_function`` scopes at the components' boundaries in the code
  (``nrt/hash_grid``, ``nrt/mlp``, ``nrt/ray_marching``, ``nrt/light_field``,
  ``nrt/medium``, ``nrt/objective/<name>/forward`` and ``.../backward``, ...; no-ops
  costing microseconds when no profiler runs, and no number changes), torch's optimizer
  scopes (``Optimizer.step#Adam.step``, ``Optimizer.zero_grad#...``) and Lightning's
  actions, which :class:`ScopeProfiler` opens as scopes while the window runs (the fetch of
  the batch, ``training_step``, the callbacks' hooks).
- The profiler nests every op and scope inside the one it ran in. An event's exclusive
  time (its duration less its children's) goes to the innermost scope around it, so a
  scope's row holds the Python and the ops inside it that no nested scope claims, and
  nothing is counted twice. The data fetch, the uncollided refresh, the adjoint and the
  Mitsuba scene build are taken whole (scopes inside them do not split them).
- Backward: each objective's backward runs inside its ``.../backward`` scope (stage 2
  backpropagates objective by objective; stage 1's Lightning backward runs in
  ``nrt/objective/photometric/backward``). Inside it, each autograd node's evaluation
  (``autograd::engine::evaluate_function: ...``) goes to the component whose scope ran the
  forward op that made the node: the profiler records the same sequence number on both. The
  rest of the backward scope (the autograd engine, the gradients' accumulation into the
  parameters) stays with the objective's row. The ``bwd`` column holds time inside backward.
- ``unattributed``: time inside the model's ``training_step`` outside every scope
  (schedules, the step's glue). The framework's rows: ``logging`` (the stages' and
  callbacks' ``self.log``, scope ``nrt/logging``), ``callbacks`` (their per-step hooks) and
  ``Lightning loop``: the rest of the window (Lightning's loop around the step and the gaps
  between events), computed as the window's wall time less every other row.

**Roofline.** Per step, FLOPs: the profiler's counts (matrix products, ``mul``, ``add``) plus
an estimate for the other elementwise ops and reductions (one per element of the
broadcast output or of the reduced input) and trilinear lookups (16 per output value);
bytes moved: every op's tensor inputs plus its (estimated) output, once each: an upper
bound of the memory traffic (caches can only lower it; gathers count the rows gathered,
not the table; ``cat`` and ``stack``, whose list shapes the profiler does not record, are
not counted). Torch ops only: Mitsuba's kernels (stage dpt) are not seen. Against two probes
measured in the same process on the same threads after training: a float32 GEMM of the
step's heaviest matrix-product shape (M, K, N) where matrix products hold at least 10 % of
its FLOPs (stage 1's MLPs), else of 8192 x 64 x 64 (an MLP layer), and a tensor add of
3 x 128 MiB (bytes read and written), each for ``--probe-seconds``. Achieved rates use the
unprofiled step time.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as nrt's commands, before torch starts

import hydra  # noqa: E402
import lightning as L  # noqa: E402
import torch  # noqa: E402
from lightning.pytorch.callbacks import Checkpoint  # noqa: E402
from lightning.pytorch.profilers import PassThroughProfiler, Profiler  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402
from torch.profiler import ProfilerActivity, record_function  # noqa: E402

from benchmarks.common import SCENES, compose_train, ea_checkpoint  # noqa: E402
from benchmarks.machine_probe import DEFAULT_GEMM, bandwidth_probe, gemm_probe  # noqa: E402
from nrt.cli.common import tune_allocator  # noqa: E402
from nrt.stages.schedules import RunClock  # noqa: E402

LABELS = {
    "data": "data (batch sampling, to device)",
    "hash_grid": "hash-grid encode",
    "mlp": "MLPs",
    "density_field": "density field, rest (activation, view SH)",
    "ray_marching": "ray marching / sampling",
    "medium": "medium (voxels composed, looked up)",
    "light_field": "light field (SH evaluation)",
    "sky_light": "sky light (MIS shadow rays)",
    "direct_light": "suns and emitters (shadow rays)",
    "compositing": "alpha compositing",
    "uncollided": "uncollided-light refresh",
    "adjoint": "adjoint coupling",
    "parametrisation": "grid parametrisation, gradient transfer",
    "render_setup": "Mitsuba scene build",
    "render": "Mitsuba render forward",
    "image_loss": "image loss (Dr.Jit)",
    "render_backward": "Mitsuba render backward",
    "optimizer": "optimizer step",
    "unattributed": "unattributed (in training_step)",
    "logging": "logging (self.log)",
    "callbacks": "callbacks",
    "loop": "Lightning loop",
}
"""Each component's row label; an objective's row is ``objective <name>``."""

STAGE_COMPONENTS = {
    "ea": ["data", "hash_grid", "mlp", "density_field", "ray_marching", "compositing",
           "objective/photometric", "optimizer"],
    "rte": ["data", "medium", "ray_marching", "light_field", "sky_light", "direct_light",
            "compositing", "uncollided", "optimizer"],
    "dpt": ["data", "parametrisation", "render", "image_loss", "render_backward", "optimizer"],
}
"""The components every profile of a stage names (stage 2 adds its objectives, and the
adjoint where it runs); every stage ends with :data:`FRAMEWORK`."""
FRAMEWORK = ["unattributed", "logging", "callbacks", "loop"]
OPAQUE = {"data", "uncollided", "adjoint", "render_setup"}
"""Components taken whole: the scopes inside them do not split them."""
GROUPS = {"data": "data", "optimizer": "optimizer", "unattributed": "unattributed",
          "logging": "framework", "callbacks": "framework", "loop": "framework"}
"""Each row's group (``model`` when not named here)."""
BACKWARD_NODE = "autograd::engine::evaluate_function"


# ------------------------------------------------------------------------ the run
class ScopeProfiler(Profiler):
    """A Lightning profiler that opens each of Lightning's actions as a torch profiler scope
    ``lightning/<action>`` (the fetch of a batch, ``training_step``, each callback's hook)
    and records nothing itself."""

    def __init__(self) -> None:
        super().__init__()
        self._open: dict[str, list[record_function]] = defaultdict(list)

    def start(self, action_name: str) -> None:
        scope = record_function(f"lightning/{action_name}")
        scope.__enter__()
        self._open[action_name].append(scope)

    def stop(self, action_name: str) -> None:
        if self._open[action_name]:
            self._open[action_name].pop().__exit__(None, None, None)

    def summary(self) -> str:
        return ""


class PinnedProgress(L.Callback, RunClock):
    """A run clock that holds the run's progress (what the stages' schedules read) at no
    less than ``at`` in [0, 1] (:func:`~nrt.stages.schedules.training_progress` takes the
    larger of the steps' share and ``seconds() / budget_s``)."""

    budget_s = 1.0

    def __init__(self, at: float):
        self.at = float(at)

    def seconds(self) -> float:
        return self.at


class StepWindows(L.Callback):
    """Times ``steps`` steps after ``warmup`` without the profiler, then ``steps`` under
    ``torch.profiler`` (with :class:`ScopeProfiler` as the trainer's profiler), and stops
    training; wall seconds by ``time.perf_counter`` at the end of each batch."""

    def __init__(self, warmup: int, steps: int):
        self.warmup, self.steps = int(warmup), int(steps)
        self.done = 0
        self.mark = 0.0
        self.plain_s = self.profiled_s = self.first_step_s = math.nan
        self.profile: torch.profiler.profile | None = None

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self.done += 1
        if pl_module.device.type == "cuda":
            torch.cuda.synchronize(pl_module.device)
        now = time.perf_counter()
        if self.done == self.warmup:
            self.mark = now
        elif self.done == self.warmup + self.steps:
            self.plain_s = now - self.mark
            trainer.profiler = ScopeProfiler()
            self.profile = torch.profiler.profile(activities=[ProfilerActivity.CPU],
                                                  record_shapes=True, with_flops=True)
            self.profile.start()
            self.mark = time.perf_counter()
        elif self.done == self.warmup + 2 * self.steps:
            self.profiled_s = now - self.mark
            self.profile.stop()
            trainer.profiler = PassThroughProfiler()
            trainer.should_stop = True


def config_overrides(args: argparse.Namespace) -> list[str]:
    """The ``nrt-train`` overrides of the run: stage, preset, scene, the EA checkpoint a
    stage that starts from one reads (``--ea-ckpt``, else :func:`ea_checkpoint`), then the
    user's."""
    overrides = [f"stage={args.stage}", f"preset={args.preset}", *SCENES[args.scene],
                 *args.overrides]
    cfg = compose_train(overrides)
    if args.stage != "ea" and OmegaConf.select(cfg, "init.source") == "ea" \
            and not OmegaConf.select(cfg, "init.ea_ckpt"):
        ckpt = args.ea_ckpt or ea_checkpoint(args.scene, args.preset)
        overrides.append(f"init.ea_ckpt={Path(ckpt).resolve()}")
    return overrides


def train(args: argparse.Namespace) -> tuple[StepWindows, L.LightningModule, int]:
    """Train as :mod:`nrt.cli.train` does for the run's steps; the windows (timings and the
    profile), the model and the trainer's ``max_steps`` (the preset's, or the run's if more)."""
    from nrt.data.family import ensure_family
    from nrt.data.render import ensure_dataset

    cfg = compose_train(config_overrides(args))
    L.seed_everything(cfg.seed, workers=True)
    model = hydra.utils.instantiate(cfg.model, _convert_="all")
    scene = OmegaConf.to_container(cfg.scene, resolve=True)
    ensure = ensure_family if scene.get("family") is not None else ensure_dataset
    dataset_dir = ensure(scene, cfg.paths.data_dir, variant=cfg.render.variant, progress=False)
    datamodule = hydra.utils.instantiate(cfg.data, dataset_dir=str(dataset_dir))
    datamodule.setup()
    windows = StepWindows(args.warmup, args.steps)
    callbacks = [PinnedProgress(args.at), windows]
    for c in cfg.callbacks.values():  # checkpoints are no part of a training step
        if not issubclass(hydra.utils.get_class(c._target_), Checkpoint):
            callbacks.append(hydra.utils.instantiate(c))
    steps = max(int(cfg.trainer.max_steps), args.warmup + 2 * args.steps)
    with tempfile.TemporaryDirectory() as tmp:
        loggers = [hydra.utils.instantiate(lg, save_dir=tmp) for lg in cfg.logger.values()]
        trainer = hydra.utils.instantiate(
            cfg.trainer, callbacks=callbacks, logger=loggers, default_root_dir=tmp,
            max_steps=steps, enable_checkpointing=False, limit_val_batches=0,
            enable_progress_bar=False, num_sanity_val_steps=0)
        trainer.fit(model, datamodule=datamodule)
    # the first step's seconds (compile=true's compilation), as nrt.callbacks.CompileHotCode
    # logs them
    windows.first_step_s = float(trainer.callback_metrics.get("time/first_step_s", math.nan))
    if windows.profile is None or math.isnan(windows.profiled_s):
        sys.exit(f"training stopped after {windows.done} steps, before the profiled window "
                 f"ended ({args.warmup + 2 * args.steps} steps)")
    return windows, model, steps


# -------------------------------------------------------------------- attribution
def classify(name: str) -> tuple[str, bool] | None:
    """The component of a scope and whether it is a backward scope; None: not a scope."""
    if name.startswith("nrt/objective/"):
        objective, _, phase = name[len("nrt/objective/"):].rpartition("/")
        return f"objective/{objective}", phase == "backward"
    if name.startswith("nrt/"):
        return name[len("nrt/"):], False
    if name.startswith("Optimizer."):
        return "optimizer", False
    if name.startswith("lightning/"):
        if name.endswith("_dataloader_next") or name.endswith(".batch_to_device"):
            return "data", False
        if name.endswith(".training_step"):
            return "unattributed", False
        return ("callbacks" if "[Callback]" in name else "loop"), False
    return None


def duration_us(event) -> float:
    return float(event.time_range.end - event.time_range.start)


def attribute(events: list, wall_us: float) -> dict[str, list[float]]:
    """Microseconds (forward, backward) per component of the profiled window (module
    docstring): the exclusive time of every event on the training thread given to the
    innermost scope around it, backward nodes to their forward op's component, the rest of
    ``wall_us`` to the Lightning loop."""
    main = next((e.thread for e in events if e.name.startswith("lightning/")
                 and e.name.endswith(".training_step")), None)
    tops = sorted((e for e in events if e.thread == main and e.cpu_parent is None),
                  key=lambda e: e.time_range.start)
    rows: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0])
    forward_of: dict[int, str] = {}  # sequence number -> component of the forward op

    def visit(event, component: str, backward: bool, opaque: bool) -> None:
        scope = None if opaque else classify(event.name)
        if scope is not None:
            component, opaque = scope[0], scope[0] in OPAQUE
            backward = backward or scope[1]
        elif event.name.startswith(BACKWARD_NODE):
            backward = True
            if not opaque:
                component = forward_of.get(event.sequence_nr, component)
        elif not backward and event.sequence_nr >= 0:
            forward_of.setdefault(event.sequence_nr, component)
        children = event.cpu_children
        rows[component][backward] += duration_us(event) - sum(map(duration_us, children))
        for child in children:
            visit(child, component, backward, opaque)

    for top in tops:
        visit(top, "loop", False, False)
    rows["loop"][0] += wall_us - sum(f + b for f, b in rows.values())
    return rows


def objective_times(events: list) -> dict[str, dict[str, float]]:
    """Inclusive microseconds of each objective's forward and backward scopes (what
    ``time/step_<name>_s`` measures, under the profiler)."""
    out: dict[str, dict[str, float]] = defaultdict(lambda: {"forward": 0.0, "backward": 0.0})
    for e in events:
        if e.name.startswith("nrt/objective/"):
            name, _, phase = e.name[len("nrt/objective/"):].rpartition("/")
            out[name][phase] += duration_us(e)
    return out


def component_table(rows: dict[str, list[float]], expected: list[str], steps: int,
                    wall_us: float) -> list[dict]:
    """The rows in milliseconds per step and shares of the profiled step, expected
    components first (zero when absent), then any other component the profile met, then
    the framework's rows."""
    names = [n for n in expected if n not in FRAMEWORK]
    names += sorted(n for n in rows if n not in names and n not in FRAMEWORK)
    table = []
    for name in names + FRAMEWORK:
        fwd, bwd = rows.get(name, (0.0, 0.0))
        table.append({
            "component": name,
            "label": LABELS.get(name, f"objective {name.partition('/')[2]}"
                                if name.startswith("objective/") else name),
            "group": GROUPS.get(name, "model"),
            "forward_ms": fwd / steps / 1e3, "backward_ms": bwd / steps / 1e3,
            "ms": (fwd + bwd) / steps / 1e3, "share": (fwd + bwd) / wall_us})
    return table


def expected_components(stage: str, model) -> list[str]:
    """The components a profile of ``stage`` names: :data:`STAGE_COMPONENTS` (stage 2's
    for stages not listed), stage 2's objectives and adjoint, and :data:`FRAMEWORK`."""
    names = list(STAGE_COMPONENTS.get(stage, STAGE_COMPONENTS["rte"]))
    names += [f"objective/{name}" for name in getattr(model, "objectives", {})]
    if getattr(model, "adjoint", None) is not None:
        names.append("adjoint")
    return names + FRAMEWORK


# ----------------------------------------------------------------------- roofline
ITEMSIZE = {"float": 4, "double": 8, "long int": 8, "int": 4, "short int": 2, "bool": 1,
            "c10::Half": 2, "c10::BFloat16": 2, "unsigned char": 1, "signed char": 1}
MATMUL = {"mm", "addmm", "bmm", "baddbmm"}
ELEMENTWISE = set(
    "add sub rsub mul div neg exp expm1 exp2 log log1p log2 sqrt rsqrt pow square reciprocal "
    "sigmoid tanh sin cos atan atan2 acos asin abs sign sgn clamp clamp_min clamp_max "
    "minimum maximum where relu threshold threshold_backward sigmoid_backward tanh_backward "
    "softplus softplus_backward floor ceil round trunc frac lerp addcmul addcdiv lt le gt ge "
    "eq ne logical_and logical_or logical_not bitwise_and bitwise_or bitwise_xor bitwise_not "
    "remainder fmod hypot erf isfinite isnan nan_to_num xlogy masked_fill uniform normal "
    "bernoulli".split())
REDUCTIONS = set("sum mean prod amax amin max min cumsum cumprod norm linalg_vector_norm any "
                 "all logsumexp var std argmax argmin".split())
GATHERS = {"index_select", "gather", "embedding"}
SCATTERS = {"index_add", "scatter_add", "index_put", "scatter", "index_copy"}
LOOKUPS = {"grid_sampler_3d", "grid_sampler_2d", "upsample_trilinear3d"}
WRITES = {"copy", "fill", "zero"}
NO_TRAFFIC = set("empty empty_strided empty_like view _reshape_alias expand expand_as "
                 "as_strided permute transpose t slice select unsqueeze squeeze narrow split "
                 "chunk unbind detach alias _unsafe_view broadcast_tensors resolve_conj "
                 "resolve_neg lift_fresh unflatten cat numpy_T item _local_scalar_dense".split())
"""Views, allocations and list inputs: no bytes counted (``reshape`` and ``flatten`` are
costed at the copy they make, if any)."""


def _tensors(event) -> list[tuple[int, int]]:
    """(numel, bytes per element) of the op's tensor inputs."""
    out = []
    for shape, dtype in zip(event.input_shapes or [], event.input_dtypes or [], strict=False):
        if dtype in ITEMSIZE and isinstance(shape, list | tuple) \
                and all(isinstance(s, int) for s in shape):
            out.append((math.prod(shape), ITEMSIZE[dtype]))
    return out


def _shapes(event) -> list[list[int]]:
    return [list(s) for s, d in zip(event.input_shapes or [], event.input_dtypes or [],
                                    strict=False) if d in ITEMSIZE]


def op_cost(event) -> tuple[float, float, float] | None:
    """(matrix-product FLOPs, other FLOPs, bytes) of one aten op by its name (module
    docstring); None for an op this table does not know (its children are costed)."""
    base = event.name[len("aten::"):].rstrip("_")
    tensors, shapes = _tensors(event), _shapes(event)
    read = float(sum(n * b for n, b in tensors))
    if base in NO_TRAFFIC:
        return 0.0, 0.0, 0.0
    if base in MATMUL and len(shapes) >= 2:
        a, b = shapes[-2], shapes[-1]  # (..., M, K) and (..., K, N)
        out = math.prod(a[:-1]) * (b[-1] if b else 1)
        flops = float(event.flops) or 2.0 * out * (a[-1] if a else 1)
        return flops, 0.0, read + 4.0 * out
    if base in ELEMENTWISE:
        try:
            out = math.prod(torch.broadcast_shapes(*[tuple(s) for s in shapes])) if shapes else 0
        except RuntimeError:
            out = max((n for n, _ in tensors), default=0)
        size = tensors[0][1] if tensors else 4
        return 0.0, float(event.flops) or float(out), read + float(out * size)
    if base in REDUCTIONS:
        return 0.0, float(tensors[0][0]) if tensors else 0.0, read
    if base in GATHERS and len(tensors) >= 2:
        (n_src, size), (n_idx, idx_size) = tensors[0], tensors[-1]
        rows = shapes[0][0] if shapes[0] else 1
        out = n_idx * (n_src // max(rows, 1)) if base != "gather" else n_idx
        return 0.0, 0.0, float(n_idx * idx_size + 2 * out * size)
    if base in SCATTERS and len(tensors) >= 2:
        rest = float(sum(n * b for n, b in tensors[1:]))
        return 0.0, float(tensors[-1][0]), rest + 2.0 * tensors[-1][0] * tensors[-1][1]
    if base in LOOKUPS and len(shapes) >= 2:
        channels = shapes[0][1] if len(shapes[0]) > 1 else 1
        out = channels * math.prod(shapes[1][:-1])
        return 0.0, 16.0 * out, read + 4.0 * out
    if base in WRITES:
        return 0.0, 0.0, read
    return None


def step_costs(events: list) -> dict[str, float]:
    """FLOPs (matrix products, other) and bytes of every aten op in the window, each op
    costed once: at the outermost op :func:`op_cost` knows, else at its children (an
    unknown op without any, a no-op ``to`` or a ``resize_``, counts nothing); the matrix
    product shape (M, K, N) with the most FLOPs."""
    total = {"matmul_flops": 0.0, "other_flops": 0.0, "bytes": 0.0}
    shapes: dict[tuple, float] = defaultdict(float)

    def visit(event) -> None:
        cost = op_cost(event) if event.name.startswith("aten::") else None
        if cost is None:
            for child in event.cpu_children:
                visit(child)
            return
        total["matmul_flops"] += cost[0]
        total["other_flops"] += cost[1]
        total["bytes"] += cost[2]
        if cost[0] > 0:
            a, b = _shapes(event)[-2:]
            shapes[(math.prod(a[:-1]), a[-1], b[-1])] += cost[0]

    for event in events:
        if event.cpu_parent is None:
            visit(event)
    total["gemm_shape"] = list(max(shapes, key=shapes.get)) if shapes else None
    return total


def roofline(events: list, steps: int, step_s: float, probe_s: float) -> dict:
    """The step's FLOPs and bytes (:func:`step_costs`) per step, the rates they reach in
    ``step_s`` seconds, and the two probes."""
    costs = step_costs(events)
    heavy = costs["matmul_flops"] >= 0.1 * (costs["matmul_flops"] + costs["other_flops"])
    shape = tuple(costs["gemm_shape"] if heavy and costs["gemm_shape"] else DEFAULT_GEMM)
    gemm, bandwidth = gemm_probe(shape, probe_s), bandwidth_probe(probe_s)
    flops = (costs["matmul_flops"] + costs["other_flops"]) / steps
    moved = costs["bytes"] / steps
    gflops, gbs = flops / step_s / 1e9, moved / step_s / 1e9
    return {"flops_per_step": flops, "matmul_flops_per_step": costs["matmul_flops"] / steps,
            "other_flops_per_step": costs["other_flops"] / steps, "bytes_per_step": moved,
            "gflops": gflops, "gbs": gbs, "intensity": flops / max(moved, 1.0),
            "gemm_probe": {"shape": list(shape), "gflops": gemm},
            "bandwidth_probe": {"gbs": bandwidth, "bytes": 3 * 4 * 2**25},
            "gemm_share": gflops / gemm, "bandwidth_share": gbs / bandwidth,
            "ridge": gemm / bandwidth}


# -------------------------------------------------------------------------- report
def machine() -> dict:
    """What the step ran on: device, CPU, cores and threads."""
    cpu = platform.processor()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f
                        if line.startswith("model name")), cpu)
    except OSError:
        pass
    affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    return {"device": "cuda" if torch.cuda.is_available() else "cpu", "cpu": cpu,
            "cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "cores": os.cpu_count(), "cores_usable": affinity,
            "torch_threads": torch.get_num_threads(),
            "torch_interop_threads": torch.get_num_interop_threads(),
            "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS"), "torch": torch.__version__}


def print_report(r: dict) -> None:
    """The report as text: header, the components' table, the objectives, the roofline."""
    m, s = r["machine"], r["step_ms"]
    print(f"profile_step: stage {r['stage']}, preset {r['preset']}, scene {r['scene']}, "
          f"progress pinned at {r['progress']:.2f}, warm-up {r['warmup']} steps, "
          f"{r['steps']} unprofiled + {r['steps']} profiled steps")
    print(f"machine: {m['device']} ({m['cpu']}, {m['cpu_capability']}), {m['cores']} cores "
          f"({m['cores_usable']} usable), torch.get_num_threads() {m['torch_threads']} "
          f"(interop {m['torch_interop_threads']}), OMP_NUM_THREADS "
          f"{m['OMP_NUM_THREADS'] or 'unset'}, torch {m['torch']}")
    refresh = r.get("uncollided_refreshes")
    print(f"step: {s['unprofiled']:.1f} ms unprofiled, {s['profiled']:.1f} ms profiled "
          f"(profiler overhead {100 * (s['profiled'] / s['unprofiled'] - 1):+.0f} %)"
          + (f"; uncollided refreshes in the profiled window: {refresh['count']} of "
             f"{r['steps']} steps (every {refresh['every']})" if refresh else ""))
    print(f"\n{'component (profiled step)':<44}{'fwd ms':>9}{'bwd ms':>9}{'ms/step':>10}"
          f"{'share':>9}")
    for row in r["components"]:
        bwd = f"{row['backward_ms']:9.2f}" if row["backward_ms"] else f"{'-':>9}"
        print(f"{row['label']:<44}{row['forward_ms']:9.2f}{bwd}{row['ms']:10.2f}"
              f"{100 * row['share']:8.1f}%")
    total = sum(row["ms"] for row in r["components"])
    print(f"{'total':<44}{'':9}{'':9}{total:10.2f}{100.0:8.1f}%")
    u = r["unattributed"]
    print(f"unattributed rest: {u['ms']:.2f} ms, {100 * u['share']:.1f} % of the step")
    if r["objectives"]:
        print("objectives, inclusive (as time/step_<name>_s): " + "; ".join(
            f"{name} {o['forward_ms']:.2f} ms forward + {o['backward_ms']:.2f} ms backward"
            for name, o in r["objectives"].items()))
    f = r["roofline"]
    gemm = " x ".join(map(str, f["gemm_probe"]["shape"]))
    side = "memory" if f["intensity"] < f["ridge"] else "compute"
    print(f"roofline (torch ops only), per step: {f['flops_per_step'] / 1e9:.4f} GFLOP "
          f"({f['matmul_flops_per_step'] / 1e9:.4f} in matrix products), "
          f"{f['bytes_per_step'] / 1e9:.4f} GB moved (an upper bound), "
          f"{f['intensity']:.3f} FLOP/B")
    print(f"  at {s['unprofiled']:.1f} ms/step (unprofiled): {f['gflops']:.2f} GFLOP/s = "
          f"{100 * f['gemm_share']:.1f} % of the GEMM probe ({f['gemm_probe']['gflops']:.1f} "
          f"GFLOP/s, {gemm}); {f['gbs']:.2f} GB/s = {100 * f['bandwidth_share']:.1f} % of "
          f"the bandwidth probe ({f['bandwidth_probe']['gbs']:.1f} GB/s, c = a + b)")
    print(f"  the probes' ridge: {f['ridge']:.2f} FLOP/B; the step is on its {side}-bound side")


def profile(args: argparse.Namespace) -> dict:
    """Run, attribute and measure (module docstring); the report as a dict."""
    windows, model, max_steps = train(args)
    events = list(windows.profile.events())
    n, wall_us = args.steps, windows.profiled_s * 1e6
    rows = attribute(events, wall_us)
    table = component_table(rows, expected_components(args.stage, model), n, wall_us)
    unattributed = next(row for row in table if row["component"] == "unattributed")
    report = {
        "stage": args.stage, "preset": args.preset, "scene": args.scene,
        "progress": args.at, "warmup": args.warmup, "steps": n, "machine": machine(),
        "step_ms": {"unprofiled": windows.plain_s / n * 1e3,
                    "profiled": windows.profiled_s / n * 1e3},
        "first_step_s": windows.first_step_s,
        "components": table,
        "unattributed": {"ms": unattributed["ms"], "share": unattributed["share"]},
        "objectives": {name: {"forward_ms": t["forward"] / n / 1e3,
                              "backward_ms": t["backward"] / n / 1e3}
                       for name, t in objective_times(events).items()},
        "roofline": roofline(events, n, windows.plain_s / n, args.probe_seconds),
        "max_steps": max_steps, "overrides": args.overrides,
    }
    cache = getattr(model, "uncollided", None)
    if cache is not None and hasattr(cache, "every"):
        first = args.warmup + n  # the profiled steps' global steps: first ... first + n - 1
        report["uncollided_refreshes"] = {
            "every": cache.every,
            "count": sum(step % cache.every == 0 for step in range(first, first + n))}
    return report


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stage", choices=("ea", "rte", "dpt"), default="rte")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--scene", choices=sorted(SCENES), default="default")
    parser.add_argument("--steps", type=int, default=20, help="steps in each timed window")
    parser.add_argument("--warmup", type=int, default=5, help="steps before the windows")
    parser.add_argument("--at", type=float, default=0.5,
                        help="the run's progress the schedules read, in [0, 1]")
    parser.add_argument("--ea-ckpt", help="the EA checkpoint stages rte and dpt start from")
    parser.add_argument("--probe-seconds", type=float, default=1.0)
    parser.add_argument("--json", type=Path, help="also write the report here")
    parser.add_argument("overrides", nargs="*", help="extra nrt-train (Hydra) overrides")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.warmup < 1 or not 0.0 <= args.at <= 1.0:
        parser.error("--steps and --warmup take at least 1 step, --at a fraction in [0, 1]")
    return args


def main(argv: list[str] | None = None) -> dict:
    """The command; returns the report it printed."""
    args = parse_args(argv)
    tune_allocator()
    report = profile(args)
    print_report(report)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1))
    return report


if __name__ == "__main__":
    main()
