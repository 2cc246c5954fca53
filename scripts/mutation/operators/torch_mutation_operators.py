"""cosmic-ray operators for the bugs torch code is prone to, found by name on parso's tree.

torch/DropDetach
    ``x.detach()`` -> ``x`` (and ``detach_``)
torch/DropClamp
    ``x.clamp(0, 1)`` -> ``x`` (clamp, clamp_, clip, clip_, clamp_min, clamp_max and their in-place forms);
    ``torch.clamp(x, 0, 1)`` -> ``(x)`` (torch.clamp, torch.clip)
torch/SwapMinMax
    ``min(a, b)`` -> ``max(a, b)`` (the builtins);
    ``x.amax(dim=1)`` -> ``x.amin(dim=1)``, ``torch.minimum(a, b)`` -> ``torch.maximum(a, b)`` (calls of
    min, max, amin, amax, minimum, maximum, fmin, fmax, nanmin, nanmax, clamp_min, clamp_max);
    ``x.clamp(min=a)`` -> ``x.clamp(max=a)``, ``x.clamp(min=a, max=b)`` -> ``x.clamp(max=a, min=b)``

Registered with cosmic-ray through the ``cosmic_ray.operator_providers`` entry point ``torch``
(pyproject.toml beside this file). ``python torch_mutation_operators.py`` checks every example.
"""

from __future__ import annotations

import parso
from parso.python.tree import Name
from parso.tree import BaseNode

from cosmic_ray.operators.operator import Example, Operator

_CLAMPS = frozenset({"clamp", "clamp_", "clip", "clip_", "clamp_min", "clamp_max", "clamp_min_", "clamp_max_"})
_SWAPS = {"min": "max", "amin": "amax", "minimum": "maximum", "fmin": "fmax", "clamp_min": "clamp_max",
          "nanmin": "nanmax"}
_SWAPS.update({v: k for k, v in list(_SWAPS.items())})


def _is_call(node) -> bool:
    return isinstance(node, BaseNode) and node.type == "trailer" and node.children[0].type == "operator" \
        and node.children[0].value == "("


def _attribute(node) -> str | None:
    """The name of an attribute trailer ``.name``, else None."""
    if isinstance(node, BaseNode) and node.type == "trailer" and len(node.children) == 2 \
            and node.children[0].type == "operator" and node.children[0].value == ".":
        return node.children[1].value
    return None


def _chains(node):
    return isinstance(node, BaseNode) and node.type in ("atom_expr", "power")


def _method_calls(node, names):
    """Indices i in an atom_expr's children where children[i] is ``.name`` (name in names) and
    children[i + 1] is a call. Index 0 is the base: a module-level function (torch.clamp) is handled apart."""
    if not _chains(node):
        return
    kids = node.children
    for i in range(1, len(kids) - 1):
        if _attribute(kids[i]) in names and _is_call(kids[i + 1]):
            yield i


def _positional_args(call):
    """The positional arguments of a call trailer, as nodes."""
    inner = call.children[1:-1]
    if not inner:
        return []
    args = inner[0].children[::2] if inner[0].type == "arglist" else [inner[0]]
    return [a for a in args if not (a.type == "argument" or (a.type == "operator" and a.value in ("*", "**")))]


class _DropMethod(Operator):
    names: frozenset[str] = frozenset()

    def _sites(self, node):
        return list(_method_calls(node, self.names))

    def mutation_positions(self, node):
        for i in self._sites(node):
            yield node.children[i].start_pos, node.children[i + 1].end_pos

    def mutate(self, node, index):
        i = self._sites(node)[index]
        node.children[i:i + 2] = []
        return node


class DropDetach(_DropMethod):
    """Remove a ``.detach()`` call: the value keeps its autograd history."""

    names = frozenset({"detach", "detach_"})

    @classmethod
    def examples(cls):
        return (
            Example("y = x.detach()\n", "y = x\n"),
            Example("y = a.b.detach().double()\n", "y = a.b.double()\n"),
            Example("y = f(x).detach() + z.detach()\n", "y = f(x) + z.detach()\n"),
            Example("y = f(x).detach() + z.detach()\n", "y = f(x).detach() + z\n", occurrence=1),
        )


class DropClamp(_DropMethod):
    """Remove a clamp/clip: ``x.clamp(...)`` -> ``x``, ``torch.clamp(x, ...)`` -> ``(x)``."""

    names = _CLAMPS

    @staticmethod
    def _function_form(node):
        kids = node.children if _chains(node) else ()
        return (len(kids) == 3 and kids[0].type == "name" and kids[0].value in ("torch", "th")
                and _attribute(kids[1]) in ("clamp", "clip") and _is_call(kids[2]) and _positional_args(kids[2]))

    def mutation_positions(self, node):
        if self._function_form(node):
            yield node.start_pos, node.end_pos
        yield from super().mutation_positions(node)

    def mutate(self, node, index):
        if self._function_form(node):
            if index == 0:
                first = _positional_args(node.children[2])[0]
                prefix = node.get_first_leaf().prefix
                atom = parso.parse("(" + first.get_code(include_prefix=False) + ")").children[0]
                atom = atom.children[0] if atom.type == "simple_stmt" else atom
                atom.get_first_leaf().prefix = prefix
                atom.parent = node.parent
                return atom
            index -= 1
        return super().mutate(node, index)

    @classmethod
    def examples(cls):
        return (
            Example("y = x.clamp(0.0, 1.0)\n", "y = x\n"),
            Example("y = x.clamp(min=0.0).sum()\n", "y = x.sum()\n"),
            Example("y = w.clip(0, 1) * 2\n", "y = w * 2\n"),
            Example("x.clamp_(max=1.0)\n", "x\n"),
            Example("y = torch.clamp(a + b, 0, 1) * 2\n", "y = (a + b) * 2\n"),
            Example("y = torch.clip(x, max=1.0)\n", "y = (x)\n"),
        )


class SwapMinMax(Operator):
    """Swap min and max: builtins, torch/numpy functions and methods, and clamp's bound keywords."""

    @staticmethod
    def _swappable(node):
        if not isinstance(node, Name) or node.value not in _SWAPS:
            return False
        parent = node.parent
        if parent is None:
            return False
        if parent.type in ("atom_expr", "power") and parent.children[0] is node:  # min(a, b)
            return node.value in ("min", "max") and len(parent.children) > 1 and _is_call(parent.children[1])
        if parent.type == "trailer" and _attribute(parent) == node.value:  # x.amax(...), torch.minimum(...)
            chain = parent.parent
            kids = chain.children
            j = kids.index(parent)
            return j + 1 < len(kids) and _is_call(kids[j + 1])
        if parent.type == "argument" and parent.children[0] is node and node.value in ("min", "max"):
            # clamp(min=a) -> clamp(max=a); clamp(min=a, max=b) -> clamp(max=a, min=b), one mutation at the first
            bounds = SwapMinMax._clamp_bounds(parent)
            return bool(bounds) and bounds[0] is node
        return False

    @staticmethod
    def _clamp_bounds(argument):
        """The min=/max= keyword names of the clamp/clip call that holds this argument, else []."""
        call = argument.parent.parent if argument.parent.type == "arglist" else argument.parent
        if not (_is_call(call) and _chains(call.parent)):
            return []
        kids = call.parent.children
        j = kids.index(call)
        if not (j > 0 and (_attribute(kids[j - 1]) in _CLAMPS or (j == 1 and kids[0].value in ("clamp", "clip")))):
            return []
        inner = call.children[1:-1]
        args = inner[0].children[::2] if inner and inner[0].type == "arglist" else inner
        return [a.children[0] for a in args
                if a.type == "argument" and a.children[0].type == "name" and a.children[0].value in ("min", "max")]

    def mutation_positions(self, node):
        if self._swappable(node):
            yield node.start_pos, node.end_pos

    def mutate(self, node, index):
        assert index == 0
        names = self._clamp_bounds(node.parent) if node.parent.type == "argument" else [node]
        for name in names:
            name.value = _SWAPS[name.value]
        return node

    @classmethod
    def examples(cls):
        return (
            Example("y = min(a, 1.0)\n", "y = max(a, 1.0)\n"),
            Example("y = x.amax(dim=1)\n", "y = x.amin(dim=1)\n"),
            Example("y = torch.minimum(a, b)\n", "y = torch.maximum(a, b)\n"),
            Example("y = x.clamp(min=0.0, max=1.0)\n", "y = x.clamp(max=0.0, min=1.0)\n"),
            Example("y = x.clamp(min=lo, max=hi).amin()\n", "y = x.clamp(min=lo, max=hi).amax()\n", occurrence=1),
            Example("y = x.clamp(min=0.0)\n", "y = x.clamp(max=0.0)\n"),
            Example("y = x.min\n", "y = x.min\n"),  # an attribute, not a call: nothing to swap
            Example("y = f(max=3)\n", "y = f(max=3)\n"),
        )


_OPERATORS = {cls.__name__: cls for cls in (DropDetach, DropClamp, SwapMinMax)}


class TorchOperatorProvider:
    """cosmic-ray operator provider ``torch``: torch/DropDetach, torch/DropClamp, torch/SwapMinMax."""

    def __iter__(self):
        return iter(_OPERATORS)

    def __getitem__(self, name):
        return _OPERATORS[name]


def _check_examples() -> int:
    from cosmic_ray.mutating import mutate_code

    bad = 0
    for name, cls in _OPERATORS.items():
        for ex in cls.examples():
            got = mutate_code(ex.pre_mutation_code, cls(**ex.operator_args), ex.occurrence)
            want = None if ex.post_mutation_code == ex.pre_mutation_code else ex.post_mutation_code
            if got != want:
                bad += 1
                print(f"{name}: {ex.pre_mutation_code!r} occurrence {ex.occurrence}: got {got!r}, want {want!r}")
    print(f"{sum(len(c.examples()) for c in _OPERATORS.values())} examples, {bad} wrong")
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(_check_examples())
