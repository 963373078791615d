"""Mutants of a Python module: one small change each, of the kinds a slip of the hand makes.

:func:`mutants` parses a module and lists every mutant of its code (docstrings, annotations,
f-strings and the arguments of ``raise`` are left alone: their changes only reword messages):

* arithmetic: ``+`` <-> ``-``, ``*`` <-> ``/``, ``//`` -> ``/``, ``%`` -> ``//``, ``**`` -> ``*``, and for
  the operators whose operands do not commute (``-``, ``/``, ``//``, ``%``, ``**``) the operands
  swapped (``pivot / spp`` -> ``spp / pivot``);
* comparisons: ``<`` <-> ``<=``, ``>`` <-> ``>=``, ``<`` <-> ``>``, ``==`` <-> ``!=``, ``is`` <-> ``is not``,
  ``in`` <-> ``not in``; ``and`` <-> ``or``; ``not x`` -> ``x``; ``-x`` -> ``x``;
* numbers: an integer ``n`` -> ``n + 1``, a float ``x`` -> ``2 x`` (0.0 -> 1.0); ``True`` <-> ``False``;
  ``min`` <-> ``max``;
* order: two neighbours swapped in a tuple or list of names (``(bare, named, others)`` ->
  ``(bare, others, named)``).

``functions`` restricts the mutants to the bodies of the named functions (``name`` or
``Class.name``). A mutant is the whole module's source, unparsed from the changed tree.
"""
from __future__ import annotations

import ast
from collections.abc import Callable, Iterator
from dataclasses import dataclass

SWAPPED_OPS = {ast.Add: ast.Sub, ast.Sub: ast.Add, ast.Mult: ast.Div, ast.Div: ast.Mult, ast.FloorDiv: ast.Div,
               ast.Mod: ast.FloorDiv, ast.Pow: ast.Mult, ast.BitAnd: ast.BitOr, ast.BitOr: ast.BitAnd,
               ast.LShift: ast.RShift, ast.RShift: ast.LShift}
NON_COMMUTING = (ast.Sub, ast.Div, ast.FloorDiv, ast.Mod, ast.Pow)
SWAPPED_COMPARISONS = {ast.Lt: (ast.LtE, ast.Gt), ast.LtE: (ast.Lt,), ast.Gt: (ast.GtE, ast.Lt), ast.GtE: (ast.Gt,),
                       ast.Eq: (ast.NotEq,), ast.NotEq: (ast.Eq,), ast.Is: (ast.IsNot,), ast.IsNot: (ast.Is,),
                       ast.In: (ast.NotIn,), ast.NotIn: (ast.In,)}


@dataclass(frozen=True)
class Mutant:
    """One change: where (line), what (``description``) and the module's changed source."""

    line: int
    description: str
    source: str


def _skipped(tree: ast.AST) -> set[int]:
    """ids of the nodes whose changes do not change behaviour (see the module notes)."""
    skip: set[int] = set()

    def under(node: ast.AST | None) -> None:
        if node is not None:
            skip.update(id(n) for n in ast.walk(node))

    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef, ast.Module)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(getattr(first.value, "value", None), str):
                under(first)
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            under(node.returns)
            for arg in (*node.args.args, *node.args.kwonlyargs, *node.args.posonlyargs,
                        node.args.vararg, node.args.kwarg):
                if arg is not None:
                    under(arg.annotation)
        elif isinstance(node, ast.AnnAssign):
            under(node.annotation)
        elif isinstance(node, (ast.JoinedStr, ast.Raise)):
            under(node)
    return skip


def _in_functions(tree: ast.Module, functions: tuple[str, ...] | None) -> set[int] | None:
    """ids of the nodes inside the named functions (None: everywhere)."""
    if functions is None:
        return None
    inside: set[int] = set()

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}{child.name}.")
            elif isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                if f"{prefix}{child.name}" in functions or child.name in functions and not prefix:
                    inside.update(id(n) for n in ast.walk(child))
            else:
                visit(child, prefix)

    visit(tree, "")
    return inside


def _changes(node: ast.AST) -> Iterator[tuple[str, Callable[[ast.AST], None]]]:
    """(description, change applied to a copy of ``node`` in place) for each mutant of ``node``."""
    if isinstance(node, (ast.BinOp, ast.AugAssign)) and type(node.op) in SWAPPED_OPS:
        new = SWAPPED_OPS[type(node.op)]
        yield f"{type(node.op).__name__} -> {new.__name__}", lambda n, new=new: setattr(n, "op", new())
        if isinstance(node, ast.BinOp) and isinstance(node.op, NON_COMMUTING):
            def swap_operands(n: ast.BinOp) -> None:
                n.left, n.right = n.right, n.left
            yield f"operands of {type(node.op).__name__} swapped", swap_operands
    elif isinstance(node, ast.Compare):
        for i, op in enumerate(node.ops):
            for new in SWAPPED_COMPARISONS.get(type(op), ()):
                def change(n: ast.Compare, i: int = i, new: type = new) -> None:
                    n.ops = [*n.ops[:i], new(), *n.ops[i + 1:]]
                yield f"{type(op).__name__} -> {new.__name__}", change
    elif isinstance(node, ast.BoolOp):
        new = ast.Or if isinstance(node.op, ast.And) else ast.And
        yield f"{type(node.op).__name__} -> {new.__name__}", lambda n, new=new: setattr(n, "op", new())
    elif isinstance(node, ast.Constant) and isinstance(node.value, bool):
        yield f"{node.value} -> {not node.value}", lambda n: setattr(n, "value", not n.value)
    elif isinstance(node, ast.Constant) and isinstance(node.value, int):
        yield f"{node.value} -> {node.value + 1}", lambda n: setattr(n, "value", n.value + 1)
    elif isinstance(node, ast.Constant) and isinstance(node.value, float):
        new_value = node.value * 2 if node.value else 1.0
        yield f"{node.value!r} -> {new_value!r}", lambda n, v=new_value: setattr(n, "value", v)
    elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("min", "max"):
        new_name = "max" if node.func.id == "min" else "min"
        yield f"{node.func.id} -> {new_name}", lambda n, v=new_name: setattr(n, "func", ast.Name(v, ast.Load()))
    elif isinstance(node, (ast.Tuple, ast.List)) and len(node.elts) > 1 and all(
            isinstance(e, (ast.Name, ast.Attribute)) for e in node.elts):
        for i in range(len(node.elts) - 1):
            def swap(n: ast.Tuple, i: int = i) -> None:
                n.elts[i], n.elts[i + 1] = n.elts[i + 1], n.elts[i]
            yield f"elements {i} and {i + 1} swapped", swap


def mutants(source: str, functions: tuple[str, ...] | None = None) -> Iterator[Mutant]:
    """Every mutant of ``source`` (module notes), in a fixed order. Each change is made on the
    parsed tree, unparsed and undone."""
    tree = ast.parse(source)
    skip, inside = _skipped(tree), _in_functions(tree, functions)
    parents = {id(child): (parent, field) for parent in ast.walk(tree) for field, value in ast.iter_fields(parent)
               for child in (value if isinstance(value, list) else [value]) if isinstance(child, ast.AST)}
    for node in ast.walk(tree):
        if id(node) in skip or (inside is not None and id(node) not in inside):
            continue
        for description, change in _changes(node):
            saved = {k: (list(v) if isinstance(v, list) else v) for k, v in vars(node).items()}
            change(node)
            yield Mutant(getattr(node, "lineno", 0), description, ast.unparse(tree))
            for k, v in saved.items():
                setattr(node, k, v)
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.Not, ast.USub)) and id(node) in parents:
            parent, field = parents[id(node)]
            value = getattr(parent, field)
            setattr(parent, field, [node.operand if v is node else v for v in value] if isinstance(value, list)
                    else node.operand)
            yield Mutant(node.lineno, f"{type(node.op).__name__} removed", ast.unparse(tree))
            setattr(parent, field, value)
