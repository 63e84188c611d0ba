"""Field expressions: the formulas a scene file writes for coefficients, sources and data.

A field is a number or a string such as ``"10*exp(-20*((x-0.3)**2 + (y-0.6)**2))"`` in the
coordinates ``x, y`` (and ``z`` in 3-D). Strings are parsed with :mod:`ast` and only a closed
set of nodes is allowed -- arithmetic, comparisons (true = 1), ``if``-expressions via
``where(c, a, b)``, the constants ``pi`` and ``e``, and the NumPy functions in
:data:`FUNCTIONS` -- so a scene file can never run arbitrary code.

A formula is at most :data:`MAX_FORMULA_LENGTH` characters long and nests at most
:data:`MAX_FORMULA_DEPTH` levels deep (``a + b + c`` nests two, ``-(-(x))`` two); a longer or
deeper one raises :class:`FormulaTooLargeError` before Python's parser or compiler could run
out of stack (``RecursionError``) or memory.

>>> import numpy as np
>>> f = compile_field("1 + (x**2 + y**2 < 0.25)", where="pde.kappa")
>>> f(np.array([[0.0, 1.0], [0.0, 1.0]])).tolist()
[2.0, 1.0]
"""

from __future__ import annotations

import ast
from collections.abc import Callable

import numpy as np

from ..errors import ResourceLimitError, SceneError

__all__ = ["FUNCTIONS", "MAX_FORMULA_DEPTH", "MAX_FORMULA_LENGTH", "ExpressionError",
           "FormulaTooLargeError", "compile_field"]

#: The longest formula accepted, in characters.
MAX_FORMULA_LENGTH = 10_000
#: The deepest nesting of operators and calls accepted (Python's compiler and the checks
#: here recurse once per level; a few hundred levels exhaust the interpreter's stack).
MAX_FORMULA_DEPTH = 200

FUNCTIONS: dict[str, Callable] = {
    name: getattr(np, name) for name in (
        "sin", "cos", "tan", "arcsin", "arccos", "arctan", "arctan2", "sinh", "cosh", "tanh",
        "exp", "log", "log10", "sqrt", "abs", "sign", "minimum", "maximum", "where", "floor",
        "ceil", "hypot")
}
# how many arguments each function takes (NumPy's extra ones, such as ``out``, are not allowed:
# ``sin(x, y)`` would write into the coordinates)
ARITY = {**dict.fromkeys(FUNCTIONS, 1), "arctan2": 2, "minimum": 2, "maximum": 2, "hypot": 2,
         "where": 3}
CONSTANTS = {"pi": np.pi, "e": np.e}
COORDINATES = ("x", "y", "z")

_ALLOWED_NODES = (
    ast.Expression, ast.BinOp, ast.UnaryOp, ast.Compare, ast.BoolOp, ast.Call, ast.Name,
    ast.Load, ast.Constant, ast.Add, ast.Sub, ast.Mult, ast.Div, ast.Pow, ast.Mod, ast.USub,
    ast.UAdd, ast.Lt, ast.LtE, ast.Gt, ast.GtE, ast.Eq, ast.NotEq, ast.And, ast.Or, ast.Not,
    ast.FloorDiv,
)


class ExpressionError(SceneError):
    """A field expression that does not parse or uses a name outside the allowed set."""


class FormulaTooLargeError(ExpressionError, ResourceLimitError):
    """A formula longer than :data:`MAX_FORMULA_LENGTH` or nested deeper than
    :data:`MAX_FORMULA_DEPTH`."""


def _shown(text: str) -> str:
    """A formula as an error message quotes it: the whole of a short one, the ends of a long
    one (a 200,000-term formula must not become a 200,000-term message)."""
    return repr(text) if len(text) <= 80 else f"{text[:40]!r} ... {text[-20:]!r}"


def _depth(tree: ast.Expression) -> int:
    """How deeply ``tree``'s expression nodes nest, its body at level 0 (counted iteratively,
    without recursion to run out of; a count past :data:`MAX_FORMULA_DEPTH` stops early)."""
    deepest, stack = 0, [(tree.body, 0)]
    while stack:
        node, depth = stack.pop()
        deepest = max(deepest, depth)
        if deepest > MAX_FORMULA_DEPTH:
            break
        stack.extend((child, depth + isinstance(child, ast.expr))
                     for child in ast.iter_child_nodes(node))
    return deepest


def _parse(value: str, where: str) -> ast.Expression:
    """``value`` parsed, or an :class:`ExpressionError` (a :class:`FormulaTooLargeError` for
    one too long or too deep)."""
    expected = (f"expected a formula of at most {MAX_FORMULA_LENGTH} characters nested at "
                f"most {MAX_FORMULA_DEPTH} levels deep")
    if len(value) > MAX_FORMULA_LENGTH:
        raise FormulaTooLargeError(f"{where} = {_shown(value)}: {len(value)} characters; "
                                   f"{expected}")
    try:
        tree = ast.parse(value.strip(), mode="eval")
    except SyntaxError as exc:
        if "too many nested" in str(exc.msg):
            raise FormulaTooLargeError(f"{where} = {_shown(value)}: {exc.msg}; "
                                       f"{expected}") from None
        raise ExpressionError(f"{where} = {_shown(value)}: not a formula ({exc.msg})") from None
    except (RecursionError, MemoryError):  # the parser's own stack ran out
        raise FormulaTooLargeError(f"{where} = {_shown(value)}: nested too deeply for the "
                                   f"parser; {expected}") from None
    if _depth(tree) > MAX_FORMULA_DEPTH:
        raise FormulaTooLargeError(f"{where} = {_shown(value)}: nested more than "
                                   f"{MAX_FORMULA_DEPTH} levels deep; {expected}")
    return tree


def _check(tree: ast.AST, text: str, where: str, dim: int) -> None:
    allowed_names = set(FUNCTIONS) | set(CONSTANTS) | set(COORDINATES[:dim])
    for node in ast.walk(tree):
        if not isinstance(node, _ALLOWED_NODES):
            raise ExpressionError(f"{where} = {_shown(text)}: {type(node).__name__} is not "
                                  "allowed in a field expression (arithmetic, comparisons and "
                                  "functions)")
        if isinstance(node, ast.Name) and node.id not in allowed_names:
            raise ExpressionError(
                f"{where} = {_shown(text)}: unknown name {node.id!r}; expected coordinates "
                f"{', '.join(COORDINATES[:dim])}, constants pi, e, or functions "
                f"{', '.join(sorted(FUNCTIONS))}")
        if isinstance(node, ast.Call) and not (isinstance(node.func, ast.Name)
                                               and node.func.id in FUNCTIONS):
            raise ExpressionError(f"{where} = {_shown(text)}: only the functions "
                                  f"{', '.join(sorted(FUNCTIONS))} can be called")
        if isinstance(node, ast.Call) and len(node.args) != ARITY[node.func.id]:
            raise ExpressionError(
                f"{where} = {_shown(text)}: {node.func.id}() called with {len(node.args)} "
                f"argument(s); expected {ARITY[node.func.id]}")
        if isinstance(node, ast.Constant) and not isinstance(node.value, int | float):
            raise ExpressionError(f"{where} = {_shown(text)}: only numeric constants are allowed")


def _float_constants(tree: ast.Expression) -> ast.Expression:
    """Integer constants as floats, in place (:func:`ast.walk` is iterative: no recursion)."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant):
            node.value = float(node.value)
    return tree


def compile_field(value: float | int | str, *, where: str,
                  dim: int = 3) -> Callable[[np.ndarray], np.ndarray]:
    """``fn(x)`` evaluating ``value`` at points ``x`` of shape ``(dim, ...)`` (float array).

    ``where`` names the scene key for error messages; ``dim`` limits the coordinates usable.
    """
    if isinstance(value, bool) or not isinstance(value, int | float | str):
        raise ExpressionError(f"{where} = {value!r}: expected a number or a formula in "
                              f"{', '.join(COORDINATES[:dim])}")
    if not isinstance(value, str):
        constant = float(value)
        if not np.isfinite(constant):
            raise ExpressionError(f"{where} = {value!r}: expected a finite number")
        return lambda x: np.full(np.shape(x)[1:], constant)
    tree = _parse(value, where)
    _check(tree, value, where, dim)
    # integer constants as floats: Python would compute 10**10**10 exactly (for ever)
    tree = _float_constants(tree)
    code = compile(tree, f"<{where}>", "eval")
    namespace = {"__builtins__": {}, **FUNCTIONS, **CONSTANTS}

    def field(x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        names = dict(zip(COORDINATES, x, strict=False))
        try:
            with np.errstate(all="ignore"):
                result = eval(code, namespace, names)
            result = np.broadcast_to(np.asarray(result, dtype=float), x.shape[1:]).copy()
        except (ArithmeticError, ValueError, TypeError) as exc:  # 1 % 0, 2.0**1e6, ...
            raise ExpressionError(f"{where} = {_shown(value)}: could not be evaluated "
                                  f"({type(exc).__name__}: {exc}); expected a formula with "
                                  "finite values") from None
        if not np.isfinite(result).all():
            first = np.argmin(np.isfinite(result).ravel())
            at = x.reshape(x.shape[0], -1)[:, first].tolist()
            raise ExpressionError(f"{where} = {_shown(value)}: non-finite value at x = {at}")
        return result

    return field
