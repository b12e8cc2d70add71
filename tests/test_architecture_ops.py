"""ops/ checks its public boundary with the one validation vocabulary (DESIGN.md, issue 22).

Rule: every public function of ``sparsetools.ops`` checks its arguments where they come in,
through :mod:`sparsetools.validate` (``check_shape``, ``check_dtype``, ``check_positive``...),
so a rule reads the same everywhere and names the parameter (``--sigma-s: must be a finite
number > 0, got 0``). Private helpers and numba kernels do not check again. What stays
hand-written is a domain rule no vocabulary function expresses ("not a rigid transform",
"N must divide L", "record was drawn for a 1242x375 image").

These tests read the source (ast), so they hold for code that is not run by any other test.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from sparsetools import validate

OPS = Path(__file__).resolve().parent.parent / "src" / "sparsetools" / "ops"

#: Modules of ops/ that do not import validate.py, and why.
EXEMPT = {
    "__init__": "the package marker, no code",
    "_jbf_kernels": "numba kernels behind jbf.jbf_expand, which checks their arguments",
    "_projection_kernels": "numba kernels behind projection.project_points*, which check",
    "_underwater_kernels": "numba kernels behind underwater.UnderwaterCompensator, which checks",
    "eld_tables": "ELD's camera calibration tables: data, no function",
}

#: Public functions taking arrays that reach no check of validate.py, and why.
UNCHECKED = {
    "mean_intrinsic_error": "averages the dicts intrinsic_error returned (no array in)",
}

#: Hand-written ``raise ParameterError`` in ops/ (domain rules, record parsing, advice such as
#: "a KITTI uint16 PNG stores depth * 256: read it with read_depth_png"). 234 before issue 22.
#: A new check that is one of the vocabulary's rules uses validate.py instead; lower this
#: number when a hand-written one goes.
MAX_HAND_WRITTEN = 66  # + ops.registration: scans Open3D cannot register (issue 23)

#: Texts of rules that validate.py owns: a hand-written raise saying one of them re-implements
#: the vocabulary (``_check_positive``, ``_range``...).
VOCABULARY_TEXTS = [
    r"must be (a )?finite",
    r"must be a number",
    r"must be a numpy array",
    r"must be one of",
    r"must be True or False",
    r"must be an? (positive )?integer",
    r"must be an odd",
    r"range is inverted",
    r"must be a \(low, high\) pair",
    r"must be in \(?\[?[-0-9.]+, [-0-9.]+",
    r"must be > 0",
    r"must be >= 0",
    r"holds NaN",
    r"is empty \(shape",
    r"\bunknown [\w ]+ ('|\{\})",
]


def _modules() -> dict[str, ast.Module]:
    return {p.stem: ast.parse(p.read_text(), str(p)) for p in sorted(OPS.glob("*.py"))}


def _imports_validate(tree: ast.Module) -> bool:
    return any(
        isinstance(node, ast.ImportFrom) and node.module == "validate" and node.level == 2
        for node in ast.walk(tree)
    )


def _functions(tree: ast.Module):
    """(name, def, public) of module-level functions and methods of module-level classes."""
    for node in tree.body:
        if isinstance(node, ast.FunctionDef):
            yield node.name, node, not node.name.startswith("_")
        elif isinstance(node, ast.ClassDef):
            for sub in node.body:
                if isinstance(sub, ast.FunctionDef):
                    public = not node.name.startswith("_") and (
                        not sub.name.startswith("_") or sub.name in ("__init__", "__post_init__")
                    )
                    yield f"{node.name}.{sub.name}", sub, public


def _called_names(fn: ast.FunctionDef) -> set[str]:
    names = set()
    for node in ast.walk(fn):
        if isinstance(node, ast.Call):
            f = node.func
            names.add(f.id if isinstance(f, ast.Name) else getattr(f, "attr", ""))
    return names


def _takes_arrays(fn: ast.FunctionDef) -> bool:
    args = fn.args.posonlyargs + fn.args.args + fn.args.kwonlyargs
    return any(a.annotation is not None and "ndarray" in ast.unparse(a.annotation) for a in args)


def _message(node: ast.Raise) -> str | None:
    """The literal text of ``raise ParameterError("...")`` (f-string parts joined)."""
    exc = node.exc
    if not (isinstance(exc, ast.Call) and getattr(exc.func, "id", "") == "ParameterError"):
        return None
    if not exc.args:
        return ""
    arg = exc.args[0]
    if isinstance(arg, ast.Constant):
        return str(arg.value)
    if isinstance(arg, ast.JoinedStr):
        return "".join(v.value if isinstance(v, ast.Constant) else "{}" for v in arg.values)
    return ast.unparse(arg)


def _hand_written(modules) -> list[tuple[str, int, str]]:
    out = []
    for mod, tree in modules.items():
        for node in ast.walk(tree):
            if isinstance(node, ast.Raise):
                text = _message(node)
                if text is not None:
                    out.append((mod, node.lineno, text))
    return out


def test_every_ops_module_with_functions_imports_validate():
    modules = _modules()
    missing = [
        mod for mod, tree in modules.items() if mod not in EXEMPT and not _imports_validate(tree)
    ]
    assert not missing, f"ops modules that do not check through validate.py: {missing}"


def test_the_exemptions_are_current():
    modules = _modules()
    stale = [m for m in EXEMPT if m not in modules or _imports_validate(modules[m])]
    assert not stale, f"EXEMPT lists modules that are gone or now import validate: {stale}"
    for mod in EXEMPT:  # an exempt module has no public function taking arrays
        public = [n for n, fn, pub in _functions(modules[mod]) if pub and _takes_arrays(fn)]
        assert not public, f"{mod} has public functions taking arrays: {public}"


def test_every_public_function_taking_arrays_reaches_a_check():
    """A public function taking arrays calls validate.py, or a function that does (its own
    private helper such as ``_check_radar``, or another public function of ops)."""
    modules = _modules()
    vocabulary = set(validate.__all__)
    defs: dict[str, list[ast.FunctionDef]] = {}
    for tree in modules.values():
        for name, fn, _ in _functions(tree):
            defs.setdefault(name.rsplit(".", 1)[-1], []).append(fn)
    checked: set[str] = set()
    changed = True
    while changed:  # fixpoint: a function checks when it calls one that checks
        changed = False
        for name, fns in defs.items():
            if name in checked:
                continue
            for fn in fns:
                calls = _called_names(fn)
                if calls & vocabulary or calls & checked:
                    checked.add(name)
                    changed = True
                    break
    unchecked = [
        f"{mod}.{name}"
        for mod, tree in modules.items()
        for name, fn, public in _functions(tree)
        if public
        and _takes_arrays(fn)
        and name.rsplit(".", 1)[-1] not in checked
        and name not in UNCHECKED
    ]
    assert not unchecked, (
        f"public ops functions that check nothing through validate.py: {unchecked}"
    )


def test_no_hand_written_raise_restates_a_vocabulary_rule():
    offenders = [
        f"ops/{mod}.py:{line}: {text!r}"
        for mod, line, text in _hand_written(_modules())
        if any(re.search(p, text) for p in VOCABULARY_TEXTS)
    ]
    assert not offenders, "use validate.py for these rules:\n" + "\n".join(offenders)


def test_hand_written_raises_do_not_come_back():
    found = _hand_written(_modules())
    assert len(found) <= MAX_HAND_WRITTEN, (
        f"{len(found)} hand-written `raise ParameterError` in ops/ (at most {MAX_HAND_WRITTEN}): "
        "a rule that validate.py has goes through validate.py"
    )


@pytest.mark.parametrize(
    "text",
    [
        "sigma_s must be finite and > 0, got 0",
        "unknown ring method 'x' (choose a, b)",
        "window must be an odd positive integer, got 4",
        "flare amount range is inverted (2 > 1)",
        "image holds NaN or infinite values",
    ],
)
def test_the_vocabulary_texts_catch_the_old_hand_written_checks(text):
    """The patterns are live: messages of the checks issue 22 replaced are caught."""
    assert any(re.search(p, text) for p in VOCABULARY_TEXTS)


# -- the functions ops added to the vocabulary -----------------------------------------------------


def test_check_points():
    import numpy as np

    from sparsetools.errors import ParameterError

    assert validate.check_points(np.zeros((5, 4), np.float32)) == 4
    assert validate.check_points(np.zeros((0, 3), np.int16)) == 3
    for bad, text in (
        (
            np.zeros((5, 2)),
            r"--points: must have shape \(N, C>=3\) with x, y, z first, got \(5, 2\)",
        ),
        (np.zeros(5), r"got \(5,\)"),
        (np.zeros((5, 3), bool), "--points: must be floating point"),
        ([[0, 0, 1]], "--points: must be an \\(N, C>=3\\) array, got list"),
    ):
        with pytest.raises(ParameterError, match=text):
            validate.check_points(bad)
    with pytest.raises(ParameterError, match="--scans: has no points"):
        validate.check_points(np.zeros((0, 3)), "scans", nonempty=True)


def test_check_values():
    import numpy as np

    from sparsetools.errors import ParameterError

    validate.check_values(np.array([0, 63]), "ring", low=0, high=63)
    validate.check_values(np.zeros(0), "ring", low=0, high=63)  # empty passes
    for a, kw, text in (
        (
            np.array([3, 70]),
            dict(low=0, high=63),
            r"--ring: values must lie in \[0, 63\], got values in \[3, 70\]",
        ),
        (
            np.array([-0.5, 2.0]),
            dict(low=0.0),
            "--depth: values must be >= 0, got a minimum of -0.5",
        ),
        (
            np.array([0.2, 1.5]),
            dict(high=1.0),
            "--depth: values must be <= 1, got a maximum of 1.5",
        ),
        (np.array([np.nan, 1.0]), dict(low=0.0), "got a minimum of nan"),
    ):
        name = "ring" if "ring" in text else "depth"
        with pytest.raises(ParameterError, match=text):
            validate.check_values(a, name, **kw)


def test_check_flag_instance_and_nonempty():
    import numpy as np

    from sparsetools.errors import ParameterError

    assert validate.check_flag(np.bool_(True), "ghosts") is True
    for bad in (1, "yes", None):
        with pytest.raises(ParameterError, match="--ghosts: must be True or False"):
            validate.check_flag(bad, "ghosts")
    assert validate.check_instance({}, "record", (dict, list)) == {}
    with pytest.raises(ParameterError, match="--record: must be a dict or list, got int"):
        validate.check_instance(3, "record", (dict, list))
    validate.check_nonempty([1], "sweeps")
    with pytest.raises(ParameterError, match="--sweeps: must hold at least one item, got none"):
        validate.check_nonempty((), "sweeps")
