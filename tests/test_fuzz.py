"""The fuzz harness in the test suite: a short run over every reader, and the inputs it ever broke.

For each target of :mod:`fuzz.targets` hypothesis draws mutations of its seed files (the choices
of :mod:`fuzz.mutate` come from a hypothesis-controlled ``random.Random``, so a failure shrinks to
a small one); each must end in a result or the command's one-line error, within the time and
memory limits, its input files unchanged (:mod:`fuzz.harness`). The run is derandomized (the
same inputs every time: CI must not turn red on a new draw; ``make fuzz`` explores). Every input
that ever failed is kept in ``fuzz/regressions/TARGET/WHAT@SEEDNAME`` and replayed here.
"""
from __future__ import annotations

import random
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fuzz.harness import run_input
from fuzz.mutate import mutate_bytes, mutate_json
from fuzz.targets import TARGET_NAMES, Context, Seed, Target, targets

REGRESSIONS = Path(__file__).resolve().parents[1] / "fuzz" / "regressions"
EXAMPLES = 60  # per target: about a minute for all of them on a quiet 2-core machine
TIME_LIMIT_S = 10.0  # per input, on a loaded CI machine (they take 0.01-0.1 s)
MEMORY_LIMIT_MB = 1024.0


@pytest.fixture(scope="module")
def prepared(tmp_path_factory: pytest.TempPathFactory) -> tuple[Context, dict[str, Target], Path]:
    root = tmp_path_factory.mktemp("fuzz")
    ctx = Context.create(root / "context")
    found = targets(ctx)
    for name, target in found.items():
        target.prepare(root / "seeds" / name)
    return ctx, found, root


@pytest.mark.parametrize("name", TARGET_NAMES)
def test_mutated_files_end_in_a_result_or_one_line(prepared, name: str) -> None:
    ctx, found, root = prepared
    target = found[name]

    @settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck))
    @given(st.randoms(use_true_random=False))
    def check(rnd: random.Random) -> None:
        outcome = run_input(target, target.mutate(rnd), root / "run" / name, ctx, TIME_LIMIT_S, MEMORY_LIMIT_MB)
        assert not outcome.failed, outcome.describe()

    check()


def _regressions() -> list[Path]:
    return sorted(p for p in REGRESSIONS.glob("*/*") if p.is_file())


@pytest.mark.parametrize("path", _regressions(), ids=lambda p: f"{p.parent.name}/{p.name}")
def test_inputs_that_once_failed(prepared, path: Path) -> None:
    ctx, found, root = prepared
    target = found[path.parent.name]
    seed_name = path.name.rpartition("@")[2]
    outcome = run_input(target, Seed(seed_name, path.read_bytes()), root / "replay", ctx, TIME_LIMIT_S,
                        MEMORY_LIMIT_MB)
    assert not outcome.failed, outcome.describe()


def test_every_target_has_seeds_that_pass(prepared) -> None:
    """The seeds themselves give results (exit 0): the mutations start from valid files."""
    ctx, found, root = prepared
    for name, target in found.items():
        for seed in target.seeds:
            if target.mutable and seed.name not in target.mutable:
                continue
            outcome = run_input(target, seed, root / "seeded" / name, ctx, TIME_LIMIT_S, MEMORY_LIMIT_MB)
            assert outcome.status == "ok", (name, seed.name, outcome.describe())


def test_mutations_are_reproducible_and_change_the_file() -> None:
    data = bytes(range(256)) * 4
    a = [mutate_bytes(data, random.Random(f"x/{i}"), hot=64) for i in range(50)]
    assert a == [mutate_bytes(data, random.Random(f"x/{i}"), hot=64) for i in range(50)]
    assert sum(m != data for m in a) >= 45
    value = {"model": {"layers": 10, "growth": 8}, "steps": [1, 2]}
    changed = [mutate_json(value, random.Random(i)) for i in range(50)]
    assert sum(c != value for c in changed) >= 40 and value == {"model": {"layers": 10, "growth": 8}, "steps": [1, 2]}
