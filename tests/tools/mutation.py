"""Mutation testing of ssgwarp's modules with mutmut 3 (a manual yardstick, not part of CI).

    pip install "mutmut>=3.8,<4"
    python tests/tools/mutation.py                      # the "data" suite: losses, cameras, lens, datasets
    python tests/tools/mutation.py services.losses capture.lens          # some modules (each runs in its suite)
    python tests/tools/mutation.py raster.rasterize raster.ops        # the "op" suite (the Python side of the rasterizer)
    python tests/tools/mutation.py capture.datasets --functions _split _evenly "SceneData.*"   # some functions of one
    python tests/tools/mutation.py --retest capture.lens        # the survivors and timeouts again (after adding tests)
    python tests/tools/mutation.py --report --survivors # the table of the results so far, and every survivor's diff

Each suite (:data:`SUITES`: modules and the tests that exercise them) runs in its own copy of the
repository, ``.mutation/<suite>/`` (git-ignored; tracked and untracked non-ignored files, re-copied
when changed), whose ``pyproject.toml`` gets the suite's ``[tool.mutmut]`` settings (changing a
suite's test list changes them: mutmut then generates the suite's mutants again and forgets its earlier
verdicts, so add tests to a listed file when only re-testing survivors). mutmut copies
the package to ``mutants/`` there and keeps each mutant's result, so an interrupted run goes on where
it stopped and a later run re-tests only what changed. Each module runs as ``nice -n 15 mutmut run
--max-children 1 "ssgwarp.<module>*"`` (low priority, one worker: the machine is shared). Per mutant,
mutmut runs only the suite's tests that call the mutated function, and stops at the first failure.

The table is markdown (docs/testing.md keeps the last one): per module the number of mutants, how many
were killed (a test failed), survived (every test passed), timed out (the tests hung: counted as
detected) or had no test calling the function, or were not checked (a run limited to some functions);
the score is ``(killed + timeout) / (mutants - not checked)``. ``--out FILE`` also writes the counts
and the survivors' names as JSON.
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
WORK = ROOT / ".mutation"
# suite -> the modules it mutates (in the order they run) and the tests run against them
SUITES = {
    "data": (("services.losses", "core.cameras", "capture.lens", "capture.datasets"),
             ("tests/test_losses.py", "tests/test_quality_measures.py", "tests/test_cameras.py", "tests/test_lens.py",
              "tests/test_datasets.py", "tests/test_colmap.py")),
    "op": (("raster.rasterize", "raster.ops"),
           ("tests/test_rasterizer.py", "tests/test_rasterizer_analytic.py", "tests/test_rasterizer_options.py",
            "tests/test_rasterizer_extremes.py", "tests/test_rasterizer_gradcheck.py", "tests/test_rasterizer_launch.py",
            "tests/test_cuda.py")),
    "matching": (("stylization.matching",), ("tests/test_stylize.py", "tests/test_matching.py")),
}
SUITE_OF = {m: s for s, (mods, _) in SUITES.items() for m in mods}
# mutmut's exit codes (mutmut/stats.py)
STATUS = {1: "killed", 3: "killed", 0: "survived", 36: "timeout", -24: "timeout", 24: "timeout", 152: "timeout",
          255: "timeout", 5: "no tests", 33: "no tests", 34: "skipped", 37: "type check", None: "not checked"}


def _mutmut_settings(suite: str) -> str:
    mods, tests = SUITES[suite]
    return "\n".join([
        "", "[tool.mutmut]  # written by tests/tools/mutation.py",
        'source_paths = ["ssgwarp/"]',
        f"only_mutate = {json.dumps([Path('ssgwarp', *m.split('.')).as_posix() + '.py' for m in mods])}",
        f"pytest_add_cli_args_test_selection = {json.dumps(list(tests))}",
        'pytest_add_cli_args = ["-p", "no:cacheprovider", "-q"]',
        'process_isolation = "forkserver"',
        # a mutant times out after (estimated test time + 10 s) x 15 of wall time (mutmut's constant, 1 s, is too
        # short on a loaded machine: pytest's start-up in the forked worker alone can take it)
        "timeout_constant = 10.0", ""])


def prepare(suite: str) -> Path:
    """``.mutation/<suite>/``: the repository's files (copied when changed, times kept, so that mutmut's
    cache of unchanged modules stays valid) and the suite's mutmut settings in its pyproject.toml."""
    where = WORK / suite
    listed = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"], cwd=ROOT,
                            capture_output=True, check=True).stdout.decode().split("\0")
    for rel in filter(None, listed):
        src, dst = ROOT / rel, where / rel
        if not src.is_file() or rel == "pyproject.toml":
            continue
        if not dst.is_file() or (dst.stat().st_mtime, dst.stat().st_size) != (src.stat().st_mtime, src.stat().st_size):
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst)
    text = (ROOT / "pyproject.toml").read_text() + _mutmut_settings(suite)
    dst = where / "pyproject.toml"
    if not dst.is_file() or dst.read_text() != text:
        dst.write_text(text)
    return where


def _mangled(module: str, function: str) -> str:
    """mutmut's name pattern for the mutants of ``function`` (``name`` or ``Class.method``) of ``module``."""
    cls, _, name = function.rpartition(".")
    return f"ssgwarp.{module}.x{'ǁ' + cls + 'ǁ' if cls else '_'}{name}__mutmut_*"


def results(module: str) -> dict[str, str]:
    """``mutant name -> status`` of ``ssgwarp/<module>.py`` from mutmut's record (empty if never run)."""
    meta = WORK / SUITE_OF[module] / "mutants" / "ssgwarp" / f"{module.replace('.', '/')}.py.meta"
    if not meta.is_file():
        return {}
    codes = json.loads(meta.read_text())["exit_code_by_key"]
    return {name: STATUS.get(code, "suspicious") for name, code in codes.items()}


def row(module: str) -> dict:
    r = results(module)
    c = Counter(r.values())
    n = len(r)
    detected = c["killed"] + c["timeout"]
    return {"module": module, "file": f"ssgwarp/{module.replace('.', '/')}.py", "mutants": n, "killed": c["killed"],
            "survived": c["survived"], "timeout": c["timeout"], "no_tests": c["no tests"],
            "not_checked": c["not checked"],
            "other": n - sum(c[k] for k in ("killed", "survived", "timeout", "no tests", "not checked")),
            "score": detected / (n - c["not checked"]) if n > c["not checked"] else float("nan"),
            "survivors": sorted(k for k, v in r.items() if v in ("survived", "no tests", "suspicious")),
            "timeouts": sorted(k for k, v in r.items() if v == "timeout")}


def table(rows: list[dict], date: str) -> str:
    lines = ["| file | mutants | killed | survived | timeout | no tests | not checked | score | date |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        lines.append(f"| `{r['file']}` | {r['mutants']} | {r['killed']} | {r['survived']} | {r['timeout']} | "
                     f"{r['no_tests']} | {r['not_checked']} | {100 * r['score']:.1f}% | {date} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("modules", nargs="*", help=f"modules of ssgwarp to mutate, among {', '.join(SUITE_OF)} "
                                               f"(default: those of the data suite)")
    ap.add_argument("--functions", nargs="+", metavar="NAME",
                    help="only these functions of the (one) module: names as in the source, methods as Class.method, "
                         "shell-style wildcards allowed")
    ap.add_argument("--retest", action="store_true", help="run only the surviving and timed-out mutants again")
    ap.add_argument("--report", action="store_true", help="only print the table of the results so far")
    ap.add_argument("--survivors", action="store_true", help="print the diff of every surviving mutant")
    ap.add_argument("--out", type=Path, help="write the counts and survivors as JSON here")
    args = ap.parse_args(argv)
    modules = args.modules or list(SUITES["data"][0])
    unknown = [m for m in modules if m not in SUITE_OF]
    if unknown:
        ap.error(f"unknown module(s) {unknown}: choose among {', '.join(SUITE_OF)}")
    if args.functions and len(modules) != 1:
        ap.error("--functions needs exactly one module")
    mutmut = shutil.which("mutmut")
    if mutmut is None:
        print('mutmut not found: pip install "mutmut>=3.8,<4"', file=sys.stderr)
        return 2
    if not args.report:
        todo = {}
        for m in modules:   # all chosen before any run: a run may reset earlier verdicts (e.g. timeouts)
            patterns = [f"ssgwarp.{m}*"] if not args.functions else [_mangled(m, f) for f in args.functions]
            if args.retest:
                again = row(m)["survivors"] + row(m)["timeouts"]   # a timeout may be the machine's load: run it again
                patterns = [n for n in again if any(fnmatch.fnmatchcase(n, p) for p in patterns)]
            todo[m] = patterns
        for m, patterns in todo.items():
            if not patterns:
                continue
            cmd = ["nice", "-n", "15", mutmut, "run", "--max-children", "1", *patterns]
            print(f"+ (in .mutation/{SUITE_OF[m]}) {' '.join(cmd[:7])} ... ({len(patterns)} patterns)", flush=True)
            subprocess.run(cmd, cwd=prepare(SUITE_OF[m]), check=False)   # survivors are no error: the table says
    date = datetime.date.today().isoformat()
    rows = [row(m) for m in modules]
    print(table(rows, date))
    if args.survivors:
        for r in rows:
            for name in r["survivors"]:
                out = subprocess.run([mutmut, "show", name], cwd=WORK / SUITE_OF[r["module"]], capture_output=True,
                                     text=True).stdout
                diff = [ln for ln in out.splitlines() if ln[:1] in "-+" and not ln.startswith(("---", "+++"))]
                print(f"\n{name} ({results(r['module'])[name]})\n" + "\n".join(diff))
    if args.out:
        args.out.write_text(json.dumps({"date": date, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
