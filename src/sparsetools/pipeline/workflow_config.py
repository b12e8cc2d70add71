"""Reading a pipeline config: a strict schema, variables without cycles, bounded expansion.

Every key is known and typed; a mistake is one error naming its place in the config
(``demo.yaml: steps[3]: unknown key 'alow_failure' (known: name, run, images, links,
allow_failure, note)``). ``${name}`` refers to ``vars:`` (and ``--set``), ``${out}`` and ``${config_dir}``; a
variable may use other variables, but never itself through a cycle, and no value may grow past
:data:`MAX_VALUE` characters. A YAML alias bomb is refused by counting the nodes the document
really holds (aliases counted each time they are used), and a step may not start another
``pipeline``/``demo`` (a config that runs itself would never end).
"""

from __future__ import annotations

import os
import re
import shlex
from pathlib import Path

from ..errors import DependencyError, FormatError

__all__ = ["MAX_CONFIG_BYTES", "MAX_NODES", "MAX_VALUE", "parse_config"]

#: Largest config file read, bytes.
MAX_CONFIG_BYTES = 1 << 20
#: Most nodes (mappings, lists, scalars; aliases counted at each use) a config may hold.
MAX_NODES = 100_000
#: Longest value after variable substitution, characters.
MAX_VALUE = 1 << 16

_VAR = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)\}")
_TOP = {"name": str, "intro": str, "vars": dict, "steps": list}
_STEP = {"name": str, "run": (str, list), "images": list, "links": list,
         "allow_failure": bool, "note": str}  # fmt: skip
_RECURSIVE = {"pipeline", "demo"}


def _read(path: Path) -> str:
    """The config's text: a regular file (a link to ``/dev/zero`` would be read forever) of
    at most :data:`MAX_CONFIG_BYTES`."""
    from ..io.sidecar import read_regular_file

    try:
        data = read_regular_file(path, what="pipeline config", max_bytes=MAX_CONFIG_BYTES)
    except FileNotFoundError as exc:
        raise FormatError(f"{path}: no such pipeline config") from exc
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise FormatError(f"{path}: cannot read the pipeline config ({exc})") from exc


def _load(path: Path, text: str):
    suffix = path.suffix.lower()
    try:
        if suffix == ".toml":
            import tomllib

            return tomllib.loads(text)
        if suffix in (".yaml", ".yml"):
            try:
                import yaml
            except ImportError:
                raise DependencyError(
                    f"{path}: a YAML pipeline config needs PyYAML: pip install "
                    "'sparsetools[yaml]' (or write the config as TOML)"
                ) from None
            return yaml.safe_load(text)
    except DependencyError:
        raise
    except Exception as exc:  # yaml.YAMLError / tomllib.TOMLDecodeError carry line numbers
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise FormatError(f"{path}: invalid config ({first})") from exc
    raise FormatError(f"{path}: pipeline config must be .yaml, .yml or .toml")


def _count_nodes(obj, path: Path) -> None:
    """Refuse documents that expand past MAX_NODES (a YAML alias bomb shares its nodes)."""
    stack, n = [obj], 0
    while stack:
        item = stack.pop()
        n += 1
        if n > MAX_NODES:
            raise FormatError(
                f"{path}: the config expands to more than {MAX_NODES} values (YAML aliases?)"
            )
        if isinstance(item, dict):
            stack.extend(item.keys())
            stack.extend(item.values())
        elif isinstance(item, list):
            stack.extend(item)


def _typename(t) -> str:
    names = {str: "a string", list: "a list", dict: "a mapping", bool: "true or false"}
    if isinstance(t, tuple):
        return " or ".join(names[x] for x in t)
    return names[t]


def _check_keys(d: dict, schema: dict, where: str) -> None:
    for key, value in d.items():
        if key not in schema:
            raise FormatError(f"{where}: unknown key {key!r} (known: {', '.join(schema)})")
        want = schema[key]
        # bool is an int, and 'false' a str: allow_failure must be a real boolean
        ok = isinstance(value, want) and not (want is str and isinstance(value, bool))
        if not ok:
            raise FormatError(
                f"{where}: {key} must be {_typename(want)}, got {type(value).__name__} "
                f"{_short(value)}"
            )


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _resolve_variables(raw: dict[str, str], where: str) -> dict[str, str]:
    """Each variable's value with the variables it uses substituted; cycles are errors."""
    done: dict[str, str] = {}

    def resolve(name: str, chain: tuple[str, ...]) -> str:
        if name in done:
            return done[name]
        if name in chain:
            cycle = " -> ".join((*chain[chain.index(name) :], name))
            raise FormatError(f"{where}: variables refer to each other in a cycle: {cycle}")
        if name not in raw:
            raise FormatError(f"{where}: unknown variable ${{{name}}}")

        def repl(m):
            return resolve(m.group(1), (*chain, name))

        value = _VAR.sub(repl, raw[name])
        if len(value) > MAX_VALUE:
            raise FormatError(f"{where}: variable {name} expands past {MAX_VALUE} characters")
        done[name] = value
        return value

    for name in raw:
        resolve(name, ())
    return done


def _substitute(text: str, variables: dict[str, str], where: str) -> str:
    def repl(m):
        key = m.group(1)
        if key not in variables:
            raise FormatError(f"{where}: unknown variable ${{{key}}}")
        return variables[key]

    value = _VAR.sub(repl, text)
    if len(value) > MAX_VALUE:
        raise FormatError(f"{where}: the value expands past {MAX_VALUE} characters")
    return value


def parse_config(
    path: str | os.PathLike, *, out_dir: str | os.PathLike, overrides: dict | None = None
) -> dict:
    """Read and check a config; return ``{"name", "intro", "steps": [step dicts]}`` with every
    variable substituted and each step's ``run`` split into arguments."""
    path = Path(path)
    cfg = _load(path, _read(path))
    _count_nodes(cfg, path)
    where = str(path)
    if not isinstance(cfg, dict):
        raise FormatError(f"{where}: a config is a mapping with a 'steps' list")
    _check_keys(cfg, _TOP, where)
    if not cfg.get("steps"):
        raise FormatError(f"{where}: config needs a non-empty 'steps' list")
    raw_vars = cfg.get("vars") or {}
    for k, v in raw_vars.items():
        if not isinstance(k, str) or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", k):
            raise FormatError(f"{where}: vars: {_short(k)} is not a variable name")
        if isinstance(v, (dict, list)) or v is None:
            raise FormatError(f"{where}: vars.{k} must be a string or a number")
    raw = {k: str(v).lower() if isinstance(v, bool) else str(v) for k, v in raw_vars.items()}
    raw.update({str(k): str(v) for k, v in (overrides or {}).items()})
    raw["out"] = str(out_dir)
    raw.setdefault("config_dir", str(path.parent))
    variables = _resolve_variables(raw, f"{where}: vars")
    steps = []
    names = set()
    for i, step in enumerate(cfg["steps"]):
        at = f"{where}: steps[{i}]"
        if not isinstance(step, dict):
            raise FormatError(f"{at}: a step is a mapping with a 'run' command line")
        _check_keys(step, _STEP, at)
        if "run" not in step:
            raise FormatError(f"{at}: each step needs a 'run' command line")
        run = step["run"]
        if isinstance(run, str):
            try:
                args = shlex.split(run)
            except ValueError as exc:
                raise FormatError(f"{at}.run: {exc} in {_short(run)}") from exc
        else:
            if not all(isinstance(a, (str, int, float)) and not isinstance(a, bool) for a in run):
                raise FormatError(f"{at}.run: a list of arguments must hold strings")
            args = [str(a) for a in run]
        args = [_substitute(a, variables, f"{at}.run") for a in args]
        if args and args[0] == "sparsetools":
            args = args[1:]
        if not args:
            raise FormatError(f"{at}.run: empty command line")
        if args[0] in _RECURSIVE:
            raise FormatError(f"{at}.run: a step may not run `sparsetools {args[0]}` (recursion)")
        images, links = step.get("images", []), step.get("links", [])
        for key, paths in (("images", images), ("links", links)):
            if not all(isinstance(p, str) for p in paths):
                raise FormatError(f"{at}.{key}: a list of paths (strings)")
        name = step.get("name", args[0])
        if name in names:
            raise FormatError(f"{at}: two steps are named {name!r}")
        names.add(name)
        steps.append(
            {
                "name": name,
                "run": args,
                "images": [_substitute(im, variables, f"{at}.images") for im in images],
                "links": [_substitute(p, variables, f"{at}.links") for p in links],
                "allow_failure": step.get("allow_failure", False),
                "note": _substitute(step.get("note", ""), variables, f"{at}.note"),
            }
        )
    return {
        "name": cfg.get("name", path.stem),
        "intro": _substitute(cfg.get("intro", ""), variables, f"{where}: intro"),
        "steps": steps,
    }
