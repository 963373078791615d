"""Budget mode's costs of the registry's models: recorded once, scaled by the host's speed now.

A time budget is a promise about wall time on the host as it is during the run, load included. So
budget mode does not trust a table as it stands: it first times two small workloads
(:func:`measure_speed`, each repeated for at least :data:`CALIBRATION_S`: a small share of any
budget) and compares them with their times recorded beside the costs: a stack of convolutions on
a 128x128 tile on torch's threads (:func:`calibration_workload`, like the networks' tiles) and
building and loading a stack of small modules on one thread (:func:`loading_workload`, like
loading a checkpoint). The two slow down differently under load: threads that wait for each other
at every layer lose more than one thread does. ``slowdown = seconds now / seconds recorded`` (2:
the host runs at half the recorded speed, because it is slower or busy) then scales the recorded
costs: the tiles' by the first, loading and the first call's by the second.

The recorded costs (``pipeline/budget_costs.json``, written by
``python -m benchmarks.budget_costs``; :class:`RecordedCosts`) hold, for each registry entry, the
seconds to load it, the extra seconds of its first call in a process (kernels prepared for new
shapes), and its seconds per tile call and per window pixel in its dearest spp range, each
measured in a process of its own and converted to the recording's calibration times. So budget
mode loads only the model it chooses, and times none of them: the costs apply where the entry's
checkpoints are those recorded and the run uses the recorded settings (CPU, ``--precision auto``,
one flip, the same native-bfloat16 support); any other model or setting is loaded and timed on
the spot (:func:`pipeline.budget.denoise_seconds`).
"""
from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from imaging.errors import DenoiserError
from imaging.json_read import parse_json
from denoise.chain import TILE_FIXED_BYTES
from denoise.tiling import cores_for_budget, plan_tiles
from model.registry import registry

COSTS = Path(__file__).resolve().with_name("budget_costs.json")
CALIBRATION_S = 0.2  # the calibration runs at least this long: it spans many of the scheduler's time slices
CALIBRATION_SIDE = 128
CALIBRATION_WIDTHS = (8, 32, 32, 32, 3)  # channels in and out of each layer
SETTINGS = {"device": "cpu", "precision": "auto", "flips": 1}  # the settings the costs are recorded at


def calibration_workload() -> Callable[[], None]:
    """One call of the calibration workload: a fixed, seeded stack of 3x3 convolutions (8 -> 32
    -> 32 -> 32 -> 3 channels, ReLU between) on a 128x128 tile, as the networks' tiles run (torch's
    threads, inference mode, layers of a size like theirs: the wait on a descheduled thread at
    each layer weighs on it as on them)."""
    import torch

    gen = torch.Generator().manual_seed(0)
    widths = CALIBRATION_WIDTHS
    layers: list[Any] = []
    for cin, cout in zip(widths, widths[1:]):
        conv = torch.nn.Conv2d(cin, cout, 3, padding=1)
        with torch.no_grad():
            conv.weight.copy_(torch.randn(conv.weight.shape, generator=gen) * 0.1)
            conv.bias.zero_()
        layers += [conv, torch.nn.ReLU()]
    net = torch.nn.Sequential(*layers[:-1]).eval()
    x = torch.rand(1, widths[0], CALIBRATION_SIDE, CALIBRATION_SIDE, generator=gen)

    def call() -> None:
        with torch.inference_mode():
            net(x)

    return call


def loading_workload() -> Callable[[], None]:
    """One call of the loading calibration: build a stack of 24 small convolutions and load its own
    weights back (Python objects and small copies on one thread, as loading a checkpoint is)."""
    import torch

    def call() -> None:
        net = torch.nn.Sequential(*[torch.nn.Conv2d(16, 16, 3, padding=1) for _ in range(24)])
        net.load_state_dict({k: v.clone() for k, v in net.state_dict().items()})

    return call


def calibrate(min_s: float = CALIBRATION_S, clock: Callable[[], float] = time.perf_counter,
              workload: Callable[[], Callable[[], None]] = calibration_workload) -> float:
    """Seconds one call of the calibration workload takes now: after a warm-up call, calls until
    ``min_s`` has passed (at least two), their mean."""
    call = workload()
    call()
    calls, start = 0, clock()
    while calls < 2 or clock() - start < min_s:
        call()
        calls += 1
    return (clock() - start) / calls


@dataclass(frozen=True)
class Speed:
    """The host's speed now: ``calibration_s`` a call of :func:`calibration_workload` and
    ``loading_s`` one of :func:`loading_workload`, against ``recorded_s`` and
    ``recorded_loading_s`` with the recorded costs (None: no costs recorded). ``slowdown`` and
    ``loading_slowdown``: the factors the recorded costs are multiplied by (1 where nothing was
    recorded)."""

    calibration_s: float
    recorded_s: float | None
    loading_s: float = 0.0
    recorded_loading_s: float | None = None

    @property
    def slowdown(self) -> float:
        return self.calibration_s / self.recorded_s if self.recorded_s else 1.0

    @property
    def loading_slowdown(self) -> float:
        return self.loading_s / self.recorded_loading_s if self.recorded_loading_s else 1.0

    def to_dict(self) -> dict[str, Any]:
        return {"calibration_s": self.calibration_s, "recorded_s": self.recorded_s,
                "slowdown": self.slowdown if self.recorded_s else None, "loading_s": self.loading_s,
                "recorded_loading_s": self.recorded_loading_s,
                "loading_slowdown": self.loading_slowdown if self.recorded_loading_s else None}


def measure_speed(recorded: tuple[float, float] | None,
                  calibrate_with: Callable[..., float] | None = None) -> Speed:
    """The host's :class:`Speed` now, against ``recorded`` (the recorded costs' calibration and
    loading calibration seconds; None: none recorded). ``calibrate_with``: :func:`calibrate`."""
    run = calibrate_with or calibrate
    return Speed(run(workload=calibration_workload), recorded[0] if recorded else None,
                 run(workload=loading_workload), recorded[1] if recorded else None)


@dataclass(frozen=True)
class EntryCost:
    """One entry's recorded seconds (at the recording's calibration time): ``load_s`` to load it,
    ``first_s`` extra on its first call in a process, ``per_call_s`` and ``per_px_s`` per tile call
    and per window pixel in its dearest spp range; what its tiles are planned from (its first
    network's ``bytes_per_pixel``, ``core_margin`` and ``alignment`` size the cores, the widest
    ``margin`` of its networks the windows), whether it needs albedo and normals, and
    ``signature``: what the figures hold for (:func:`entry_signature`)."""

    load_s: float
    first_s: float
    per_call_s: float
    per_px_s: float
    bytes_per_pixel: float
    core_margin: int
    margin: int
    alignment: int
    needs_aovs: bool
    signature: tuple[str, ...]

    def tiles(self, height: int, width: int, max_memory_mb: float) -> tuple[int, int]:
        """(tiles, window pixels) of an HxW image under the memory bound, as the loaded entry
        plans them (:meth:`denoise.denoiser.Denoiser.cores`)."""
        core = cores_for_budget(height, width, self.bytes_per_pixel, max_memory_mb * 2**20 - TILE_FIXED_BYTES,
                                self.core_margin, self.alignment, minimum=16)
        windows = [(t.wy1 - t.wy0) * (t.wx1 - t.wx0) for t in plan_tiles(height, width, core, self.margin)]
        return len(windows), sum(windows)

    def denoise_s(self, height: int, width: int, max_memory_mb: float, speed: Speed | None = None) -> float:
        """Predicted seconds to denoise an HxW image in a process where it has not run yet, on a
        host of ``speed`` (None: as recorded): the first call's extra at its loading slowdown, the
        tiles at its slowdown."""
        tiles, pixels = self.tiles(height, width, max_memory_mb)
        slowdown, loading = (speed.slowdown, speed.loading_slowdown) if speed else (1.0, 1.0)
        return loading * self.first_s + slowdown * (self.per_call_s * tiles + self.per_px_s * pixels)


def entry_signature(name: str) -> tuple[str, ...]:
    """What an entry's recorded costs hold for: each of its members' spec with its checkpoint's
    SHA-256 (from the manifest)."""
    reg = registry()
    sha = {card.file: card.sha256 for card in reg.checkpoints.values()}
    return tuple(f"{m.spec} {sha.get(m.path.name, '?')}" for m in reg.select(name).members)


@dataclass(frozen=True)
class RecordedCosts:
    """``pipeline/budget_costs.json`` read: ``calibration_s`` and ``loading_s`` of the
    recording's calibrations, the ``settings`` and ``native_bfloat16`` it was recorded with, and
    the ``entries``' costs."""

    calibration_s: float
    loading_s: float
    settings: Mapping[str, Any]
    native_bfloat16: bool
    entries: Mapping[str, EntryCost]

    def usable(self, device: str, precision: str, flips: int, native_bfloat16: bool) -> bool:
        """True when a run with these settings on this CPU runs what was recorded."""
        return (dict(self.settings) == {"device": device, "precision": precision, "flips": flips}
                and self.native_bfloat16 == native_bfloat16)

    def entry(self, name: str) -> EntryCost | None:
        """The entry's costs, or None when it was not recorded or its members changed since."""
        cost = self.entries.get(name)
        return cost if cost is not None and cost.signature == entry_signature(name) else None


class CostsError(DenoiserError):
    """The recorded costs file is unusable."""


def read_costs(path: str | Path = COSTS) -> RecordedCosts | None:
    """The recorded costs (None when the file does not exist); raises :class:`CostsError`."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        data = parse_json(path.read_text())
        entries = {name: EntryCost(float(e["load_s"]), float(e["first_s"]), float(e["per_call_s"]),
                                   float(e["per_px_s"]), float(e["bytes_per_pixel"]), int(e["core_margin"]),
                                   int(e["margin"]), int(e["alignment"]), bool(e["needs_aovs"]),
                                   tuple(e["signature"]))
                   for name, e in data["entries"].items()}
        return RecordedCosts(float(data["calibration_s"]), float(data["loading_calibration_s"]), dict(data["settings"]),
                             bool(data["machine"]["native_bfloat16"]), entries)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise CostsError(f"{path}: not a usable budget costs file ({type(exc).__name__}: {exc})") from None
