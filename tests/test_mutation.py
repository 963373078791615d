"""The mutation tester: its operators make the changes they promise (the three slips found by hand
among them), and its runner tells killed mutants from survivors."""
from __future__ import annotations

import ast
from pathlib import Path

from mutation.operators import mutants
from mutation.runner import Module, run_module

ROOT = Path(__file__).resolve().parents[1]


def _changed_lines(original: str, mutant: str) -> list[str]:
    """The mutant's statements that differ from the original's (both unparsed alike)."""
    before = ast.unparse(ast.parse(original)).splitlines()
    after = mutant.splitlines()
    return [b.strip() for a, b in zip(before, after) if a != b]


def test_each_kind_of_change() -> None:
    source = ("def f(a, b, xs):\n"
              "    if a < b and not xs:\n"
              "        return max(a - b, 0.5) ** 2\n"
              "    for item in (a, b, xs):\n"
              "        pass\n"
              "    return -a, a is None, a in xs, True\n")
    found = {m.description: _changed_lines(source, m.source) for m in mutants(source)}
    assert found["Lt -> LtE"] == ["if a <= b and (not xs):"]
    assert found["Lt -> Gt"] == ["if a > b and (not xs):"]
    assert found["And -> Or"] == ["if a < b or not xs:"]
    assert found["Not removed"] == ["if a < b and xs:"]
    assert found["max -> min"] == ["return min(a - b, 0.5) ** 2"]
    assert found["operands of Sub swapped"] == ["return max(b - a, 0.5) ** 2"]
    assert found["operands of Pow swapped"] == ["return 2 ** max(a - b, 0.5)"]
    assert found["Pow -> Mult"] == ["return max(a - b, 0.5) * 2"]
    assert found["0.5 -> 1.0"] == ["return max(a - b, 1.0) ** 2"]
    assert found["2 -> 3"] == ["return max(a - b, 0.5) ** 3"]
    assert found["elements 1 and 2 swapped"] == ["for item in (a, xs, b):"]
    assert found["USub removed"] == ["return (a, a is None, a in xs, True)"]
    assert found["Is -> IsNot"] == ["return (-a, a is not None, a in xs, True)"]
    assert found["In -> NotIn"] == ["return (-a, a is None, a not in xs, True)"]
    assert found["True -> False"] == ["return (-a, a is None, a in xs, False)"]


def test_messages_docstrings_and_annotations_are_left_alone() -> None:
    source = ('def f(a: int = 3) -> float:\n    """Docstring 1."""\n'
              '    if a > 1:\n        raise ValueError(f"a {a + 1} > 1")\n    return a\n')
    assert sorted(m.description for m in mutants(source)) == ["1 -> 2", "3 -> 4", "Gt -> GtE", "Gt -> Lt"]


def test_the_slips_found_by_hand_are_among_the_mutants() -> None:
    def sources(path: str, functions: tuple[str, ...] | None = None) -> list[str]:
        return [m.source for m in mutants((ROOT / path).read_text(), functions)]

    assert any("np.exp(-0.5 * (t * sigma) ** 2)" in s for s in sources("imaging/metrics.py"))
    assert any("return max(1.0, spp / pivot_spp)" in s for s in sources("denoise/noise_guard.py"))
    assert any("for candidates in (bare, others, named):" in s
               for s in sources("imaging/exr_layers.py", ("pick_color_layer",)))


def test_functions_restrict_the_mutants() -> None:
    source = "def f():\n    return 1\n\nclass C:\n    def g(self):\n        return 2\n"
    assert [m.description for m in mutants(source, ("C.g",))] == ["2 -> 3"]
    assert [m.description for m in mutants(source, ("f",))] == ["1 -> 2"]


def test_the_runner_kills_what_the_tests_see(tmp_path: Path) -> None:
    """A toy module whose test checks one value: the mutants that change it die, the others live."""
    (tmp_path / "toy.py").write_text("def gap(a, b):\n    return a - b if a > b else 0\n")
    (tmp_path / "test_toy.py").write_text("from toy import gap\n\ndef test_gap():\n    assert gap(3, 1) == 2\n")
    result = run_module(Module("toy.py", ("test_toy.py",)), tmp_path, lambda text: None)
    survived = sorted(s["change"] for s in result["survived"])
    assert (result["mutants"], result["killed"], survived) == (5, 3, ["0 -> 1", "Gt -> GtE"])
    assert result["score"] == 0.6 and (tmp_path / "toy.py").read_text().startswith("def gap(a, b):\n    return a - b")
