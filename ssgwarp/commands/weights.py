"""``ssgwarp weights``: where each pretrained model is found, its size and licence; ``--download`` fetches them
(the table: :mod:`ssgwarp.services.weights_command`)."""
from __future__ import annotations

import argparse
import sys
from typing import Iterable, Mapping

from ..errors import SsgwarpError
from ..services.weight_specs import GROUPS, SPECS, _spec
from ..services.weights import DownloadFailed, fetch, find, locate, offline_reason, verbose
from ..services.weights_command import table


def _expand(names: Iterable[str]) -> list[str]:
    out: list[str] = []
    for n in names:
        for k in GROUPS.get(n, (n,)):
            _spec(k)
            if k not in out:
                out.append(k)
    return out


_GROUPS_HELP = ", ".join(g + " = " + " + ".join(v) for g, v in GROUPS.items())


# -- `ssgwarp weights` ----------------------------------------------------------------------------------
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--download", nargs="*", metavar="NAME", default=None,
                   help=f"fetch these models into the Hugging Face / torch hub caches (all when no NAME): "
                        f"{', '.join(SPECS)}, or a group: {_GROUPS_HELP}")
    p.add_argument("--force", action="store_true", help="with --download: fetch again even when cached")
    p.add_argument("--verify", action="store_true",
                   help="check the found files against their published hashes (reads every file)")


def run(args) -> int:
    with verbose():            # this command is where the long forms belong
        return _run(args)


def _run(args) -> int:
    cfg = getattr(args, "weights", None)
    cfg = cfg if isinstance(cfg, Mapping) else None
    if args.download is not None:
        keys = _expand(args.download) if args.download else list(SPECS)
        off = offline_reason()
        if off:
            raise SsgwarpError(f"--download: downloads are off ({off}); run it on a machine with network "
                               f"without --offline / SSGWARP_OFFLINE / HF_HUB_OFFLINE")
        failed = []
        for key in keys:
            if not args.force and locate(key, config=cfg) is not None:
                print(f"ssgwarp weights: {key} already here ({find(key, config=cfg)})")
                continue
            try:
                fetch(key, force=args.force)
            except DownloadFailed as e:
                failed.append(key)
                print(f"ssgwarp weights: {e}", file=sys.stderr)
        print(table(config=cfg, check=args.verify))
        if failed:
            raise SsgwarpError(f"could not download {', '.join(failed)} (see the messages above)")
        return 0
    print(table(config=cfg, check=args.verify))
    return 0
