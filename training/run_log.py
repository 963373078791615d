"""A run's JSON-lines log (``RUN_DIR/log.jsonl``) and its training-curve plot (``curves.png``).

Each line is one JSON object with a ``type`` and the ``step`` it describes:
``{"type": "train", "step": 500, "loss": 0.012, "lr": 0.01, "skipped": 0, "patches_per_s": 95.1}``
and ``{"type": "val", "step": 2000, "psnr": 31.2, "relmse": 0.004, "per_spp": {...}}``.
Non-finite numbers are written as null (strict JSON).
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from imaging.atomic_io import atomic_path, json_safe, write_text_atomic
from imaging.json_read import parse_json


class RunLog:
    """Append-only JSON-lines log; :meth:`truncate_after` rewinds it for ``--resume``."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def append(self, record: dict[str, Any]) -> None:
        """Append one record as a JSON line and flush it."""
        try:
            with open(self.path, "a", encoding="utf-8") as fh:
                fh.write(json.dumps(json_safe(record), allow_nan=False) + "\n")
        except OSError as exc:  # e.g. a full disk: name the log (a torn line is skipped by read())
            raise OSError(exc.errno, exc.strerror or str(exc), str(self.path)) from None

    def read(self) -> list[dict[str, Any]]:
        """All complete records (a torn last line from a crash is ignored)."""
        if not self.path.exists():
            return []
        records = []
        for line in self.path.read_text(encoding="utf-8").splitlines():
            try:
                records.append(parse_json(line))
            except json.JSONDecodeError:
                continue
        return records

    def truncate_after(self, step: int) -> None:
        """Drop records of steps after ``step`` (written after the checkpoint being resumed)."""
        kept = [r for r in self.read() if int(r.get("step", 0)) <= step]
        write_text_atomic(self.path, "".join(json.dumps(r, allow_nan=False) + "\n" for r in kept))


def validation_curve(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The validations of a run's log, each with the optimisation CPU minutes at its step (from the
    train record of the same step; validations without one are left out): ``{"step", "cpu_min",
    "psnr", "per_spp": {spp: ours}, "noisy": {spp: dB}, "oidn": {spp: dB or None}}``."""
    cpu = {r["step"]: r.get("cpu_s") for r in records if r.get("type") == "train"}
    curve = []
    for r in records:
        if r.get("type") == "val" and cpu.get(r["step"]) is not None:
            per_spp = r.get("per_spp", {})
            curve.append({"step": r["step"], "cpu_min": cpu[r["step"]] / 60, "psnr": r["psnr"],
                          **{who: {spp: v["psnr"][name] for spp, v in per_spp.items()}
                             for who, name in (("per_spp", "ours"), ("noisy", "noisy"), ("oidn", "oidn"))}})
    return curve


def plot_curves(records: list[dict[str, Any]], path: str | Path) -> None:
    """Plot training loss and validation PSNR per spp (ours vs noisy vs OIDN) to a PNG, atomically."""
    import matplotlib
    from matplotlib.figure import Figure  # no pyplot: no global backend state, renders with Agg

    train = [r for r in records if r.get("type") == "train" and r.get("loss") is not None]
    val = [r for r in records if r.get("type") == "val"]
    fig = Figure(figsize=(11, 4))
    ax_loss, ax_val = fig.subplots(1, 2)
    ax_loss.plot([r["step"] for r in train], [r["loss"] for r in train], lw=1)
    ax_loss.set(xlabel="step", ylabel="loss (transfer space)", title="training loss")
    if train and min(r["loss"] for r in train) > 0:
        ax_loss.set_yscale("log")
    spps = sorted({int(s) for r in val for s in r.get("per_spp", {})})
    colors = matplotlib.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, spp in enumerate(spps):
        color = colors[i % len(colors)]
        rows = [(r["step"], r["per_spp"][str(spp)]["psnr"]) for r in val if str(spp) in r.get("per_spp", {})]
        steps = [s for s, _ in rows]
        for name, style in (("ours", "-"), ("noisy", ":"), ("oidn", "--")):
            values = [m.get(name) for _, m in rows]
            if any(v is not None for v in values):
                ax_val.plot(steps, [math.nan if v is None else v for v in values], style, color=color,
                            marker="o" if name == "ours" else None, ms=3,
                            label=f"{spp} spp {name}")
    ax_val.set(xlabel="step", ylabel="PSNR (dB, tonemapped)", title="validation")
    if spps:
        ax_val.legend(fontsize=7, ncol=max(1, len(spps) // 2))
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
