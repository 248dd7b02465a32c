"""Presets: a set of option values as one flag (``--quick``, a command's CPU-sized preset; ``stylize --paint``).

:func:`add_preset` adds such a flag to a command's parser; it sets each option of the preset that the
command line (or ``--config``) left at its default, so an option given explicitly, before or after the
flag, wins. :func:`add_quick` adds ``--quick``.
"""
from __future__ import annotations

import argparse
from typing import Any, Mapping


class AtMost(int):
    """A preset's image width: at most this many pixels. A capture already narrower keeps its own size, so
    that no preset raises a capture's resolution (``reconstruct --quick`` on a 200x200 capture trains at
    200x200, not 252x252); ``--width N`` given explicitly is taken as it is."""

    at_most = True


class _Preset(argparse.Action):
    def __init__(self, option_strings, dest, preset: Mapping[str, Any], defaults: Mapping[str, Any], **kw):
        super().__init__(option_strings, dest, nargs=0, default=False, **kw)
        self.preset, self.defaults = dict(preset), dict(defaults)

    def __call__(self, parser, namespace, values, option_string=None):
        for dest, value in self.preset.items():
            if getattr(namespace, dest, None) == self.defaults[dest]:
                setattr(namespace, dest, value)
        setattr(namespace, self.dest, True)


def add_preset(parser: argparse.ArgumentParser, flag: str, preset: Mapping[str, Any], help: str) -> None:
    """Add ``flag``: the ``preset`` option values (by dest) unless given explicitly. ``{values}`` in ``help``
    becomes the values as they read in ``--help``. Call after the preset's options are added."""
    flags = {a.dest: a.option_strings[0] for a in parser._actions if a.option_strings}
    unknown = [d for d in preset if d not in flags]
    if unknown:
        raise ValueError(f"{flag} preset names unknown options: {unknown}")
    text = ", ".join(f"{flags[d]} {v}" + (" (at most: never wider than the capture)" if getattr(v, "at_most", False)
                                          else "") for d, v in preset.items())
    parser.add_argument(flag, action=_Preset, preset=preset, defaults={d: parser.get_default(d) for d in preset},
                        help=help.replace("{values}", text).replace("%", "%%"))


def add_quick(parser: argparse.ArgumentParser, preset: Mapping[str, Any], measured: str) -> None:
    """Add ``--quick``: the ``preset`` option values (by dest) unless given explicitly; ``measured`` says what
    the preset costs (shown in ``--help``). Call after the preset's options are added."""
    add_preset(parser, "--quick", preset, "CPU-sized preset: {values} (options given explicitly win); " + measured)


def preset_values(parser: argparse.ArgumentParser, dest: str) -> dict[str, Any]:
    """The option values of the preset flag whose dest is ``dest`` in ``parser`` (empty if it is no preset)."""
    act = next((a for a in parser._actions if a.dest == dest), None)
    return dict(act.preset) if isinstance(act, _Preset) else {}


def quick_text(preset: Mapping[str, Any]) -> str:
    """The preset as it reads on a command line (``--iters 150 --path-frames 20``)."""
    return " ".join(f"--{d.replace('_', '-')} {v}" for d, v in preset.items())
