"""The machine a benchmark ran on, for its JSON result, and writing that result."""

from __future__ import annotations

import json
from pathlib import Path


def cpu_model() -> dict:
    """CPU model and widest SIMD from /proc/cpuinfo (the fast backend's speed follows it)."""
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
    return {"cpu_model": fields.get("model name", ""), "simd": simd}


def write_result(result: dict, out: Path) -> None:
    """Write a benchmark's result as indented JSON to ``out`` (its folder created) and say so."""
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print("wrote", out)
