"""Old option spellings, kept for one release: they work and print one deprecation warning
naming the new spelling (:func:`deprecated`); :data:`DEPRECATED` lists them all."""

from __future__ import annotations

import functools
import logging

import click

__all__ = ["DEPRECATED", "deprecated", "warn_deprecated"]


#: Old spelling -> the option that replaces it, per command (filled by :func:`deprecated`);
#: the architecture test checks that every hidden option is one of these and that it warns.
DEPRECATED: dict[tuple[str, str], str] = {}
_DEPRECATED_KEY = "sparsetools.deprecated"


def warn_deprecated(text: str) -> None:
    """One deprecation warning line on stderr (once per message and run)."""
    ctx = click.get_current_context(silent=True)
    seen = ctx.find_root().meta.setdefault("sparsetools.warned", set()) if ctx else set()
    if text in seen:
        return
    seen.add(text)
    logging.getLogger("sparsetools.cli").warning("deprecated: %s", text)


def deprecated(
    old: str,
    new: str,
    *,
    command: str,
    dest: str,
    value=None,
    is_flag: bool = False,
    convert=None,
    metavar: str | None = None,
):
    """A hidden alias ``old`` of option ``new`` (stored in parameter ``dest``): it still works
    for one release and prints a one-line warning naming ``new``.

    The old text goes through ``new``'s own type and callback, so it is read exactly as the
    new option reads it; ``convert(text) -> text`` first rewrites it where the syntax changed
    too (``train --crop HxW`` -> ``--crop-size WxH``). ``value`` (for a flag) is the new
    option's value the old flag means (``--no-confidence`` -> ``--conf-format none``). Giving
    both spellings is a usage error.
    """
    DEPRECATED[(command, old)] = new

    def remember(ctx, param, given):
        if given is None or (is_flag and not given):
            return
        ctx.meta.setdefault(_DEPRECATED_KEY, {})[old] = given

    def deco(f):
        @functools.wraps(f)
        def command_fn(*args, **kw):
            ctx = click.get_current_context()
            store = ctx.meta.get(_DEPRECATED_KEY, {})
            if old in store:
                from click.core import ParameterSource

                if ctx.get_parameter_source(dest) not in (None, ParameterSource.DEFAULT):
                    raise click.UsageError(f"{old} is the old spelling of {new}: give {new} only")
                warn_deprecated(f"{old} is now {new} (the old spelling goes in 0.4)")
                if value is not None:
                    kw[dest] = value
                else:
                    target = next(p for p in ctx.command.params if p.name == dest)
                    text = store[old]
                    if convert is not None:
                        try:
                            text = convert(text)
                        except (TypeError, ValueError) as exc:
                            raise click.BadParameter(str(exc), param_hint=old) from None
                    try:
                        kw[dest] = target.process_value(ctx, text)
                    except click.BadParameter as exc:
                        exc.param_hint = old  # name what the user typed
                        raise
                ctx.set_parameter_source(dest, ParameterSource.COMMANDLINE)  # given, as typed
            return f(*args, **kw)

        return click.option(
            old,
            is_flag=is_flag,
            default=None,
            hidden=True,
            metavar=metavar,
            expose_value=False,
            callback=remember,
            help=f"Deprecated: use {new}.",
        )(command_fn)

    return deco
