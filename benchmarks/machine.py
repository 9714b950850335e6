"""The machine a benchmark ran on, for its JSON result, and writing that result."""

from __future__ import annotations

import json
from pathlib import Path

#: committed results: what a full run writes unless ``--out`` says otherwise
RESULTS = Path(__file__).resolve().parent / "results"
#: where a ``--quick`` (smoke) run writes unless ``--out`` says otherwise: ``outputs/`` is git-ignored
QUICK_RESULTS = Path(__file__).resolve().parents[1] / "outputs" / "benchmarks_quick"


def default_out(name: str, quick: bool) -> Path:
    """The result path ``name`` (a file, or "" for the folder itself) of a run without ``--out``:
    under benchmarks/results/, or for a ``--quick`` run, whose figures mean little, under
    outputs/benchmarks_quick/ (never beside the committed results)."""
    return (QUICK_RESULTS if quick else RESULTS) / name


def out_help(name: str) -> str:
    """The help of ``--out`` where :func:`default_out` gives its default ``name``."""
    if not name:
        return "result folder (default: benchmarks/results; with --quick outputs/benchmarks_quick)"
    return f"result file (default: benchmarks/results/{name}; with --quick outputs/benchmarks_quick/{name})"


def cpu_model() -> dict:
    """CPU model, family (CPUs of one name differ by generation: AMD EPYC family 23 is Zen 1-2,
    25 Zen 3-4, 26 Zen 5) and widest SIMD from /proc/cpuinfo (the fast backend's speed
    follows them)."""
    try:
        info = Path("/proc/cpuinfo").read_text()
    except OSError:
        return {}
    fields = {}
    for line in info.splitlines():
        if not line.strip():
            break  # the first processor's block is enough
        key, _, value = line.partition(":")
        fields[key.strip()] = value.strip()
    flags = set(fields.get("flags", "").split())
    simd = next((f for f in ("avx512f", "avx2", "avx", "sse4_2") if f in flags), "none")
    family = f"{fields.get('cpu family', '?')}/{fields.get('model', '?')}"
    return {"cpu_model": fields.get("model name", ""), "cpu_family_model": family, "simd": simd}


def avx2_features() -> str:
    """This CPU's LLVM feature string with every AVX-512 and AVX10 feature turned off: as
    ``NUMBA_CPU_FEATURES``, numba then compiles the code an AVX2-only CPU would get."""
    import llvmlite.binding as llvm

    features = llvm.get_host_cpu_features()
    off = {name for name in features if name.startswith(("avx512", "avx10", "amx-avx512"))}
    return ",".join(("+" if on and name not in off else "-") + name for name, on in sorted(features.items()))


def write_result(result: dict, out: Path) -> None:
    """Write a benchmark's result as indented JSON to ``out`` (its folder created) and say so."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print("wrote", out)
