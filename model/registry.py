"""The shipped models by name: what ``--model`` and ``Denoiser(...)`` accept, and each one's card.

``model/weights/manifest.json`` holds the registry: the checkpoints (file, SHA-256, architecture
preset, the spp they were trained on, the recipe that makes them) and the entries a user chooses
from, each named for what it is for:

* ``fast``, ``balanced``, ``high``: each a set of checkpoints, every one limited to the spp of the
  renders it runs on (the expert spec syntax, :mod:`denoise.ensemble`, kept inside the entry), and
  what runs when a render's spp is unknown (``unknown_spp``: the entry's own measured choice);
* ``auto``: per render, the cheapest entry whose measured PSNR at the nearest measured spp is within
  :data:`AUTO_TOLERANCE_DB` of the best entry's (the entry named ``default`` when the spp is
  unknown); under a time budget, budget mode chooses among the entries instead
  (:mod:`pipeline.budget`).

The figures of the cards (PSNR at 4/16/128 spp and FLIP at 16 on ../shared/eval-scenes, time as a
ratio to OIDN's) are written into the manifest by ``python -m benchmarks.model_cards`` from the
benchmark result files, never typed (tests/test_model_cards.py compares them).

A ``--model`` value is, in this order: a registry name; an existing file (a checkpoint written by
``train``); an expert spec ``A+B[+...]`` of members ``NAME[:LO-HI]`` where NAME is a checkpoint of
the registry (``unet-l-allspp``), a name a shipped checkpoint had before (``u-high``, and ``fast`` for
``flat-s``: inside a spec a name is always a checkpoint, so the specs written before the registry
run what they ran), or a path; else an error that lists the valid names.
"""
from __future__ import annotations

import functools
import json
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from imaging.errors import DenoiserError

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
MANIFEST = WEIGHTS_DIR / "manifest.json"
AUTO = "auto"
AUTO_TOLERANCE_DB = 0.1  # auto: an entry this close to the best at an spp is "level" with it
SEPARATOR = "+"  # the expert spec's member separator (denoise.ensemble.SEPARATOR)
CARD_SPP = (4, 16, 128)  # the spp of the cards' PSNR figures
_SPP_RANGE = re.compile(r"^(?P<model>.+):(?P<lo>\d*)-(?P<hi>\d*)$")  # ``unet-l:17-``


class RegistryError(DenoiserError):
    """A model name that the registry does not know, or a manifest that cannot be used."""


@dataclass(frozen=True)
class CheckpointCard:
    """One shipped checkpoint: ``file`` in the weights folder, its ``sha256``, the architecture
    ``preset`` it was built from, ``trained_spp`` (LO, HI; 0: no limit) of its training renders,
    the ``recipe`` that makes it, the ``pixel_filter`` of its training renders and what its
    training was (``training``: stages, steps, CPU-minutes, data), as recorded."""

    name: str
    file: str
    sha256: str
    preset: str
    description: str
    trained_spp: tuple[int, int]
    recipe: str
    pixel_filter: str = "box"
    training: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Entry:
    """A registry entry: ``members`` (an expert spec of checkpoint names with spp ranges) run on
    renders of known spp; where the spp is unknown, ``unknown_tiers`` choose by the image's own
    noise level (:mod:`denoise.image_noise`): the first tier whose bound the level is below runs
    (a flat image: the first), each a spec whose members may name their float format
    (``NAME@bfloat16``); ``purpose`` says what it is chosen for; ``figures``: its card's figures."""

    name: str
    purpose: str
    members: str
    unknown_tiers: tuple[tuple[float, str], ...]
    figures: Mapping[str, Any] = field(default_factory=dict)

    @property
    def unknown_spp(self) -> str:
        """The unknown-spp choice in words."""
        return "; ".join(spec if math.isinf(bound) else f"{spec} below noise level {bound:g}"
                         for bound, spec in self.unknown_tiers)

    def psnr(self, spp: int) -> float | None:
        """Its measured mean PSNR (dB) on the eval scenes at ``spp``, if measured."""
        value = (self.figures.get("psnr") or {}).get(str(spp))
        return None if value is None else float(value)

    def time_ratio(self, spp: int | None = None) -> float | None:
        """Its time over OIDN's, if measured: at ``spp`` where that was measured (the largest over
        image sizes), else at its dearest spp (the largest measured ratio)."""
        value = (self.figures.get("time_by_spp") or {}).get(str(spp)) if spp is not None else None
        value = self.figures.get("time_ratio") if value is None else value
        return None if value is None else float(value)

    def help_line(self) -> str:
        """One line for ``--help`` and ``--list-models``: name, purpose and the figures it has."""
        psnr = [self.psnr(s) for s in CARD_SPP]
        parts = [f"{self.name}: {self.purpose}"]
        if all(p is not None for p in psnr):
            parts.append(f"{'/'.join(f'{p:.2f}' for p in psnr)} dB at {'/'.join(map(str, CARD_SPP))} spp")
        if self.time_ratio() is not None:
            parts.append(f"{self.time_ratio():.2f}x OIDN's time")
        return "; ".join(parts)


@dataclass(frozen=True)
class Member:
    """One network of a selection: a checkpoint file limited to renders of ``lo``..``hi`` spp
    (0: no limit), and the name it was given by (a registry checkpoint, a retired name, a path)."""

    path: Path
    lo: int = 0
    hi: int = 0
    given: str = ""
    precision: str | None = None  # ``NAME@PRECISION``: its float format (None: the caller's)

    @property
    def spec(self) -> str:
        """``NAME[:LO-HI][@PRECISION]``: what resolves to it again."""
        suffix = f"@{self.precision}" if self.precision else ""
        return f"{self.given or self.path}{range_suffix(self.lo, self.hi)}{suffix}"


@dataclass(frozen=True)
class Choice:
    """What one entry or spec runs: ``by_spp`` on renders of known spp (each member where its range
    and training cover the spp; :class:`denoise.denoiser.Network`); where the spp is unknown, the
    members of the first of ``unknown_tiers`` whose bound the image's own noise level is below
    (None: the spec's own rule, those trained on every spp, else its first member)."""

    name: str
    by_spp: tuple[Member, ...]
    unknown_tiers: tuple[tuple[float, tuple[Member, ...]], ...] | None = None

    def for_unknown_spp(self, level: float) -> tuple[Member, ...] | None:
        """The members for an image of unknown spp whose noise level is ``level`` (NaN: a flat
        image, the first tier's)."""
        if not self.unknown_tiers:
            return None
        return next((members for bound, members in self.unknown_tiers if not level >= bound),
                    self.unknown_tiers[-1][1])

    @property
    def unknown_members(self) -> tuple[Member, ...]:
        return tuple(m for _, members in self.unknown_tiers or () for m in members)


@dataclass(frozen=True)
class Selection:
    """What a ``--model`` value names: ``name`` (what a command prints, and ``--model`` accepts
    back), one choice or, for ``auto``, one per entry (the registry picks per render)."""

    name: str
    choices: tuple[Choice, ...]
    auto: bool = False
    entry: bool = False  # a registry entry (or ``auto``), not a file or an expert spec of the same name

    @property
    def members(self) -> list[Member]:
        """Every distinct member of every choice, in order of first appearance."""
        seen: dict[Member, None] = {}
        for choice in self.choices:
            for member in (*choice.by_spp, *choice.unknown_members):
                seen.setdefault(member, None)
        return list(seen)


def training_line(card: CheckpointCard) -> str:
    """How a checkpoint was trained, in words, from its card's ``training`` record: a recipe run
    (from nothing, every stage recording) gives the hours and hardware of the whole lineage up to
    this file (each stage to the best step the next one started from); any other file its own
    run's, and what it was warm-started from."""
    rec = card.training
    hours = rec.get("hours") or {}
    gpu = f", {float(hours['gpu']):g} GPU-hours" if float(hours.get("gpu") or 0) else ""
    where = ", ".join(rec.get("hardware") or [])
    # "finetune": training.recipe.FINETUNE, a stage started from a given file (model/ sits below training/)
    if hours and rec.get("recipe_stage") and rec["recipe_stage"] != "finetune":
        return (f"trained: {float(hours.get('cpu') or 0):g} CPU-hours{gpu} from nothing to this file, on "
                f"{where or 'hardware not recorded'}: stage {rec['recipe_stage']} of `train --recipe {card.recipe}`")
    steps = f"{rec['steps']:,} steps, " if rec.get("steps") else ""
    minutes = f"{rec['cpu_minutes']:g} CPU-minutes" if rec.get("cpu_minutes") else "CPU time not recorded"
    run = "in one run from scratch" if not rec.get("warm_start") else f"in its last run, from {rec['warm_start']}"
    unrecorded = " and ".join(part for part in ("earlier runs" if rec.get("warm_start") else "",
                                              "" if where else "hardware") if part)
    return (f"trained: {steps}{minutes}{' on ' + where if where else ''} {run}"
            f"{f' ({unrecorded} not recorded)' if unrecorded else ''}; recipe: `train --recipe {card.recipe}`")


def range_suffix(lo: int, hi: int) -> str:
    """The ``:LO-HI`` of a member limited to an spp range (an end of 0 left out); ``""`` for none."""
    return f":{lo or ''}-{hi or ''}" if lo or hi else ""


def split_member(member: str) -> tuple[str, int, int, str | None]:
    """``NAME[:LO-HI][@PRECISION]`` -> (NAME, LO, HI, PRECISION or None); see :func:`split_range`."""
    name, at, precision = member.rpartition("@")
    if not at or not precision.isalnum():
        return (*split_range(member), None)
    return (*split_range(name), precision)


def split_range(member: str) -> tuple[str, int, int]:
    """``NAME:LO-HI`` -> (NAME, LO, HI): it runs only on renders of LO to HI spp (either end may be
    left out: ``unet-l:17-``; 0: no limit); a member without a range -> (member, 0, 0). Raises
    :class:`RegistryError` for a range with neither end or with LO > HI."""
    match = _SPP_RANGE.match(member)
    if match is None:
        return member, 0, 0
    lo, hi = int(match["lo"] or 0), int(match["hi"] or 0)
    if not (lo or hi) or (hi and lo > hi):
        raise RegistryError(f"model member {member!r}: expected NAME:LO-HI spp with LO <= HI "
                            "(one end may be left out)")
    return match["model"], lo, hi


@dataclass(frozen=True)
class Registry:
    """The manifest, read: ``entries`` by name, ``checkpoints`` by name, ``retired`` (names that
    checkpoints had before, -> a registry checkpoint or, when no longer shipped, the commit that
    holds the file), the ``default`` entry, the ``folder`` the files are in, and the ``license``
    the weights are under (an SPDX name: the project's, LICENSE)."""

    default: str
    entries: Mapping[str, Entry]
    checkpoints: Mapping[str, CheckpointCard]
    retired: Mapping[str, str]
    folder: Path
    sources: Mapping[str, Any] = field(default_factory=dict)
    license: str = ""

    @classmethod
    def load(cls, path: Path = MANIFEST) -> Registry:
        """Read and check a manifest; raises :class:`RegistryError` naming the file and the problem."""
        try:
            data = json.loads(Path(path).read_text())
            checkpoints = {name: CheckpointCard(name=name, file=c["file"], sha256=c["sha256"], preset=c["preset"],
                                                description=c["description"],
                                                trained_spp=(int(c["trained_spp"][0]), int(c["trained_spp"][1])),
                                                recipe=c["recipe"], pixel_filter=c.get("pixel_filter", "box"),
                                                training=c.get("training", {}))
                           for name, c in data["checkpoints"].items()}
            entries = {name: Entry(name=name, purpose=e["purpose"], members=e["members"],
                                   unknown_tiers=tuple((float(tier.get("below", math.inf)), tier["run"])
                                                       for tier in e["unknown_spp"]),
                                   figures=e.get("figures", {}))
                       for name, e in data["entries"].items()}
            registry = cls(default=data["default"], entries=entries, checkpoints=checkpoints,
                           retired=dict(data.get("retired", {})), folder=Path(path).parent,
                           sources=data.get("sources", {}), license=str(data.get("license", "")))
        except OSError as exc:
            raise RegistryError(f"{path}: cannot read the model registry ({exc.strerror or exc})") from None
        except (ValueError, KeyError, TypeError, IndexError, AttributeError) as exc:
            raise RegistryError(f"{path}: not a model registry manifest ({type(exc).__name__}: {exc})") from None
        registry.check()
        return registry

    def check(self) -> None:
        """Raise :class:`RegistryError` unless the default is an entry, entry names and checkpoint
        names do not overlap, and every entry's members name registry checkpoints."""
        if self.default not in self.entries:
            raise RegistryError(f"registry default {self.default!r} is not an entry ({', '.join(self.entries)})")
        clash = (set(self.entries) | {AUTO}) & (set(self.checkpoints) | {AUTO} & set(self.entries))
        if clash:
            raise RegistryError(f"registry names mean two things: {', '.join(sorted(clash))}")
        for entry in self.entries.values():
            bounds = [bound for bound, _ in entry.unknown_tiers]
            if not bounds or bounds != sorted(bounds) or not math.isinf(bounds[-1]):
                raise RegistryError(f"registry entry {entry.name!r}: unknown_spp needs tiers of rising 'below' "
                                    "bounds, the last without one")
            for spec in (entry.members, *(spec for _, spec in entry.unknown_tiers)):
                for member in spec.split(SEPARATOR):
                    name = split_member(member.strip())[0]
                    if name not in self.checkpoints:
                        raise RegistryError(f"registry entry {entry.name!r}: {name!r} is not a registry checkpoint")

    @property
    def names(self) -> list[str]:
        """What ``--model`` takes by name: the entries, then ``auto``."""
        return [*self.entries, AUTO]

    def path_of(self, name: str) -> Path | None:
        """The file of a registry checkpoint or of a retired name that maps to one; None for any
        other name. Raises :class:`RegistryError` for a retired name no longer shipped."""
        target = self.retired.get(name, name)
        if target in self.checkpoints:
            return self.folder / self.checkpoints[target].file
        if name in self.retired:
            raise RegistryError(f"model {name!r} is no longer shipped; its file is in git: `git show "
                                f"{target}:model/weights/{name}.ckpt > {name}.ckpt`, then --model {name}.ckpt")
        return None

    def member(self, text: str) -> Member:
        """One expert-spec member ``NAME[:LO-HI][@PRECISION]`` (NAME: registry checkpoint, retired
        name or path)."""
        if Path(text).is_file():
            return Member(Path(text), given=text)
        name, lo, hi, precision = split_member(text)
        path = self.path_of(name)
        if path is None:
            path = Path(name)
            if path.exists() and not path.is_file():
                raise RegistryError(f"cannot read {name}: a folder, not a checkpoint file")
            if not path.is_file():
                if path.suffix or len(path.parts) > 1:
                    raise RegistryError(f"{name}: checkpoint file not found")
                raise RegistryError(f"unknown model {name!r} (registry names: {', '.join(self.names)}; "
                                    f"checkpoints: {', '.join(self.checkpoints)})")
        return Member(path, lo, hi, name, precision)

    def spec_members(self, spec: str) -> tuple[Member, ...]:
        """The members of an expert spec ``A+B[+...]`` (or one member)."""
        parts = [p.strip() for p in spec.split(SEPARATOR)]
        if not all(parts):
            raise RegistryError(f"model ensemble {spec!r}: expected MODEL+MODEL[+...] with no empty member")
        return tuple(self.member(p) for p in parts)

    def entry(self, name: str) -> Entry:
        if name not in self.entries:
            raise RegistryError(f"unknown model {name!r} (registry names: {', '.join(self.names)})")
        return self.entries[name]

    def entry_choice(self, name: str) -> Choice:
        """The :class:`Choice` of a registry entry."""
        entry = self.entry(name)
        return Choice(name, self.spec_members(entry.members),
                      tuple((bound, self.spec_members(spec)) for bound, spec in entry.unknown_tiers))

    def select(self, model: str | Path | None) -> Selection:
        """The :class:`Selection` of a ``--model`` value (None: the default entry; see the module
        docstring for the order). Raises :class:`RegistryError` listing the valid names."""
        text = str(self.default if model is None else model).strip()
        if not text:
            raise RegistryError(f"empty model name (registry names: {', '.join(self.names)})")
        if text == AUTO:
            return Selection(AUTO, tuple(self.entry_choice(n) for n in self.entries), auto=True, entry=True)
        if text in self.entries:
            return Selection(text, (self.entry_choice(text),), entry=True)
        if Path(text).is_file():
            return Selection(text, (Choice(text, (Member(Path(text), given=text),)),))
        members = self.spec_members(text)
        return Selection(text, (Choice(text, members),))

    def select_list(self, items: list[str]) -> Selection:
        """The :class:`Selection` of a list of members (files or ``NAME[:LO-HI]``; a ``+`` in a
        file's name is part of it)."""
        if not items or not all(str(i).strip() for i in items):
            raise RegistryError(f"model ensemble {list(map(str, items))!r}: expected models, no empty member")
        members = tuple(self.member(str(i).strip()) for i in items)
        name = SEPARATOR.join(map(str, items))
        return Selection(name, (Choice(name, members),))

    def auto_entry(self, spp: int | None) -> str:
        """``auto``'s entry for a render of ``spp``: among the entries measured at the measured spp
        nearest to it (in log2; a tie takes the larger), the cheapest there (:meth:`Entry.time_ratio`)
        whose PSNR is within :data:`AUTO_TOLERANCE_DB` of the best; the default entry when the spp
        is unknown or nothing is measured."""
        measured = sorted({int(s) for e in self.entries.values() for s in (e.figures.get("psnr") or {})})
        if spp is None or not measured:
            return self.default
        nearest = min(measured, key=lambda s: (abs(math.log2(s) - math.log2(spp)), -s))
        scored = [(e.psnr(nearest), e.time_ratio(nearest), e.name) for e in self.entries.values()
                  if e.psnr(nearest) is not None and e.time_ratio(nearest) is not None]
        if not scored:
            return self.default
        best = max(p for p, _, _ in scored)
        return min((t, n) for p, t, n in scored if p >= best - AUTO_TOLERANCE_DB)[1]

    @staticmethod
    def spec_words(spec: str) -> str:
        """The members of a spec without ranges, each ``NAME`` or ``NAME (PRECISION)``, joined by `` + ``."""
        words = []
        for text in spec.split(SEPARATOR):
            cname, _, _, precision = split_member(text.strip())
            words.append(cname + (f" ({precision})" if precision else ""))
        return " + ".join(words)

    def spp_ranges(self, spec: str) -> list[tuple[int, int, list[str]]]:
        """What an expert spec runs at each spp, as a person reads it: (LO, HI, members as
        ``NAME`` or ``NAME (PRECISION)``) for consecutive spp ranges from 1 (HI 0: no limit). A
        member runs where its range and its checkpoint's trained spp (:class:`CheckpointCard`)
        both cover the spp, as :meth:`denoise.denoiser.Denoiser.active` does; where none does,
        the first member runs."""
        members = []
        for text in spec.split(SEPARATOR):
            cname, lo, hi, precision = split_member(text.strip())
            t_lo, t_hi = self.checkpoints[cname].trained_spp if cname in self.checkpoints else (0, 0)
            ends = [n for n in (hi, t_hi) if n]
            members.append((max(lo, t_lo, 1), min(ends, default=0), cname + (f" ({precision})" if precision else "")))
        bounds = sorted({1, *(lo for lo, _, _ in members), *(hi + 1 for _, hi, _ in members if hi)})
        ranges: list[tuple[int, int, list[str]]] = []
        for start, stop in zip(bounds, [*bounds[1:], 0]):
            running = [words for lo, hi, words in members if lo <= start and (not hi or start <= hi)]
            running = list(dict.fromkeys(running or [members[0][2]]))
            if ranges and ranges[-1][2] == running:
                ranges[-1] = (ranges[-1][0], stop - 1 if stop else 0, running)
            else:
                ranges.append((start, stop - 1 if stop else 0, running))
        return ranges

    def card(self, name: str) -> str:
        """A registry entry's card as text: purpose, the networks that run at each spp, the
        unknown-spp choice, figures, and each checkpoint's architecture, training and recipe."""
        entry = self.entry(name)
        ranges = self.spp_ranges(entry.members)
        several = any(len(running) > 1 for _, _, running in ranges)
        lines = [entry.help_line() + (" (the default)" if name == self.default else ""),
                 "  runs, by the render's spp" + (" (two or more networks: their outputs weighted per pixel by "
                                                  "their estimated errors; averaged where the render has no "
                                                  "variance)" if several else "") + ":"]
        lines += [f"    {spp_words(lo, hi)}: {' + '.join(running)}" for lo, hi, running in ranges]
        lines.append("  runs, spp unknown: " + ", else ".join(
            f"{self.spec_words(spec)}{'' if math.isinf(bound) else f' where the image noise level is below {bound:g}'}"
            for bound, spec in entry.unknown_tiers))
        fig = entry.figures
        if fig.get("flip"):
            lines.append(f"  FLIP at 16 spp: {float(fig['flip']['16']):.3f}" if "16" in fig["flip"] else "")
        if fig.get("time"):
            lines.append("  time: " + ", ".join(f"{size} {float(t['ratio']):.2f}x OIDN at {t['spp']} spp"
                                                for size, t in fig["time"].items()))
        specs = SEPARATOR.join((entry.members, *(spec for _, spec in entry.unknown_tiers)))
        for cname in dict.fromkeys(split_member(m.strip())[0] for m in specs.split(SEPARATOR)):
            c = self.checkpoints[cname]
            spp = "every spp" if c.trained_spp == (0, 0) else \
                f"{c.trained_spp[0] or 1}-{c.trained_spp[1] or ''} spp"
            lines.append(f"  {cname}: {c.description}; preset {c.preset}; trained on {spp}, "
                         f"{c.pixel_filter} filter; recipe {c.recipe}; sha256 {c.sha256[:12]}")
            lines.append(f"    {training_line(c)}")
        for key in ("scoreboard", "inference"):
            if key in self.sources:
                lines.append(f"  figures: {self.sources[key]}")
        if self.license:
            lines.append(f"  licence: the weights are under {self.license}, as the code (the project's LICENSE file)")
        return "\n".join(line for line in lines if line)


def spp_words(lo: int, hi: int) -> str:
    """An spp range in words: ``1-16 spp``, ``17+ spp``, ``8 spp``."""
    if not hi:
        return f"{lo}+ spp"
    return f"{lo} spp" if lo == hi else f"{lo}-{hi} spp"


@functools.lru_cache(maxsize=4)
def _load(path: Path) -> Registry:
    return Registry.load(path)


def registry(path: Path | None = None) -> Registry:
    """The registry of ``path`` (default: the shipped manifest, :data:`MANIFEST`), read once."""
    return _load(Path(path or MANIFEST))
