"""Mutation testing of ssgwarp's modules with mutmut 3 (a manual yardstick, not part of CI).

    pip install "mutmut>=3.8,<4"
    python tests/tools/mutation.py                      # the modules of MODULES, one after the other
    python tests/tools/mutation.py losses lens          # some of them
    python tests/tools/mutation.py datasets --functions _split _evenly "SceneData.*"   # some functions of one
    python tests/tools/mutation.py --retest lens        # run the survivors again (after adding tests)
    python tests/tools/mutation.py --report             # only the table of the results already in mutants/
    python tests/tools/mutation.py --report --survivors # ... and the diff of every surviving mutant

mutmut's settings (which files, which tests) are ``[tool.mutmut]`` in pyproject.toml; it copies the
package to ``mutants/`` (git-ignored) and writes each mutant's result there, so an interrupted run goes
on where it stopped, and a run after a change re-tests only what changed. Each module runs as
``nice -n 15 mutmut run --max-children 1 "ssgwarp.<module>*"`` (low priority, one worker: the machine
is shared). Per mutant, mutmut runs only the selected tests that call the mutated function, and stops
at the first failure.

The table is markdown (docs/testing.md keeps the last one): per module the number of mutants, how many
were killed (a test failed), survived (every test passed), timed out (the tests hung: counted as
detected) or had no test calling the function, or were not checked (a run limited to some functions);
the score is ``(killed + timeout) / (mutants - not checked)``.
``--out FILE`` also writes the counts and the survivors' names as JSON.
"""
from __future__ import annotations

import argparse
import datetime
import fnmatch
import json
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
# the modules in [tool.mutmut] only_mutate, in the order they are run
MODULES = ("losses", "cameras", "lens", "datasets", "matching", "rasterize", "ops")
# mutmut's exit codes (mutmut/stats.py)
STATUS = {1: "killed", 3: "killed", 0: "survived", 36: "timeout", -24: "timeout", 24: "timeout", 152: "timeout",
          255: "timeout", 5: "no tests", 33: "no tests", 34: "skipped", 37: "type check", None: "not checked"}


def _mangled(module: str, function: str) -> str:
    """mutmut's name pattern for the mutants of ``function`` (``name`` or ``Class.method``) of ``module``."""
    cls, _, name = function.rpartition(".")
    return f"ssgwarp.{module}.x{'ǁ' + cls + 'ǁ' if cls else '_'}{name}__mutmut_*"


def results(module: str) -> dict[str, str]:
    """``mutant name -> status`` of ``ssgwarp/<module>.py`` from mutmut's record (empty if never run)."""
    meta = ROOT / "mutants" / "ssgwarp" / f"{module}.py.meta"
    if not meta.is_file():
        return {}
    codes = json.loads(meta.read_text())["exit_code_by_key"]
    return {name: STATUS.get(code, "suspicious") for name, code in codes.items()}


def row(module: str) -> dict:
    r = results(module)
    c = Counter(r.values())
    n = len(r)
    detected = c["killed"] + c["timeout"]
    return {"module": module, "file": f"ssgwarp/{module}.py", "mutants": n, "killed": c["killed"], "survived": c["survived"],
            "timeout": c["timeout"], "no_tests": c["no tests"], "not_checked": c["not checked"],
            "other": n - sum(c[k] for k in ("killed", "survived", "timeout", "no tests", "not checked")),
            "score": detected / (n - c["not checked"]) if n > c["not checked"] else float("nan"),
            "survivors": sorted(k for k, v in r.items() if v in ("survived", "no tests", "suspicious"))}


def table(rows: list[dict], date: str) -> str:
    lines = ["| file | mutants | killed | survived | timeout | no tests | not checked | score | date |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        lines.append(f"| `{r['file']}` | {r['mutants']} | {r['killed']} | {r['survived']} | {r['timeout']} | "
                     f"{r['no_tests']} | {r['not_checked']} | {100 * r['score']:.1f}% | {date} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("modules", nargs="*", help=f"modules of ssgwarp to mutate (default: {' '.join(MODULES)})")
    ap.add_argument("--functions", nargs="+", metavar="NAME",
                    help="only these functions of the (one) module: names as in the source, methods as Class.method, "
                         "shell-style wildcards allowed")
    ap.add_argument("--retest", action="store_true", help="run only the surviving mutants again")
    ap.add_argument("--report", action="store_true", help="only print the table of the results in mutants/")
    ap.add_argument("--survivors", action="store_true", help="print the diff of every surviving mutant")
    ap.add_argument("--out", type=Path, help="write the counts and survivors as JSON here")
    args = ap.parse_args(argv)
    modules = args.modules or list(MODULES)
    unknown = [m for m in modules if m not in MODULES]
    if unknown:
        ap.error(f"unknown module(s) {unknown}: choose among {', '.join(MODULES)} (pyproject [tool.mutmut])")
    mutmut = shutil.which("mutmut")
    if mutmut is None:
        print('mutmut not found: pip install "mutmut>=3.8,<4"', file=sys.stderr)
        return 2
    if args.functions and len(modules) != 1:
        ap.error("--functions needs exactly one module")
    if not args.report:
        for m in modules:
            patterns = [f"ssgwarp.{m}*"] if not args.functions else [_mangled(m, f) for f in args.functions]
            if args.retest:
                patterns = [n for n in row(m)["survivors"] if not args.functions
                            or any(fnmatch.fnmatchcase(n, p) for p in patterns)]
                if not patterns:
                    continue
            cmd = ["nice", "-n", "15", mutmut, "run", "--max-children", "1", *patterns]
            print("+", " ".join(cmd), flush=True)
            subprocess.run(cmd, cwd=ROOT, check=False)   # a survivor is not an error: the table says it
    date = datetime.date.today().isoformat()
    rows = [row(m) for m in modules]
    print(table(rows, date))
    if args.survivors:
        for r in rows:
            for name in r["survivors"]:
                out = subprocess.run([mutmut, "show", name], cwd=ROOT, capture_output=True, text=True).stdout
                diff = [ln for ln in out.splitlines() if ln[:1] in "-+" and not ln.startswith(("---", "+++"))]
                print(f"\n{name} ({results(r['module'])[name]})\n" + "\n".join(diff))
    if args.out:
        args.out.write_text(json.dumps({"date": date, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
