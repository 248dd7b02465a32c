"""benchmarks/kernel_counters.py folds Nsight Compute's CSV (one row per launch and metric) into one
row per kernel launch, in microseconds, with readable kernel names."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import kernel_counters as kc  # noqa: E402

WARP = "batched_forward_kernel__locals__blend_forward_batched_b3d75266_cuda_kernel_forward"
GSPLAT = "void gsplat::rasterize_to_pixels_3dgs_fwd_kernel<3, float>(unsigned int, const vec<2, float, 0> *)"
CUB = "void cub::_V_300403_SM_900::detail::radix_sort::DeviceRadixSortOnesweepKernel<Policy, false>(int *)"
HEAD = ('"ID","Process ID","Process Name","Host Name","Kernel Name","Context","Stream","Block Size",'
        '"Grid Size","Device","CC","Section Name","Metric Name","Metric Unit","Metric Value"')


def row(i, kernel, metric, unit, value):
    return (f'"{i}","1","python3","127.0.0.1","{kernel}","1","7","(256, 1, 1)","(8160, 1, 1)","0","9.0",'
            f'"Command line profiler metrics","{metric}","{unit}","{value}"')


def test_parse_folds_metrics_per_launch_and_converts_durations():
    text = "\n".join([
        "==PROF== Connected to process 1", HEAD,
        row(0, WARP, "gpu__time_duration.sum", "msecond", "1.21"),
        row(0, WARP, "smsp__inst_executed.sum", "inst", "816,749,371"),
        row(0, WARP, "launch__registers_per_thread", "register/thread", "48"),
        row(1, GSPLAT, "gpu__time_duration.sum", "usecond", "972.5"),
        row(1, GSPLAT, "smsp__inst_executed.sum", "inst", "832,838,207"),
        row(1, GSPLAT, "dram__bytes.sum", "byte", "12"),  # (a metric not asked for: left out)
        row(2, CUB, "gpu__time_duration.sum", "nsecond", "3500"),
        row(3, CUB, "gpu__time_duration.sum", "ns", "1,221,504"),
        "==PROF== Disconnected from process 1",
    ])
    rows = kc.parse(text)
    assert [r["id"] for r in rows] == [0, 1, 2, 3]
    assert abs(rows[0]["gpu__time_duration.sum"] - 1210.0) < 1e-9 and rows[0]["smsp__inst_executed.sum"] == 816749371
    assert rows[0]["launch__registers_per_thread"] == 48
    assert rows[1]["gpu__time_duration.sum"] == 972.5 and "dram__bytes.sum" not in rows[1]
    assert rows[2]["gpu__time_duration.sum"] == 3.5 and abs(rows[3]["gpu__time_duration.sum"] - 1221.504) < 1e-9
    assert kc.parse("==PROF== no kernels were profiled") == []


def test_short_names():
    assert kc.short(WARP) == "blend_forward_batched"
    assert kc.short(GSPLAT) == "rasterize_to_pixels_3dgs_fwd_kernel"
    assert kc.short(CUB) == "DeviceRadixSortOnesweepKernel"
