"""Which Numba codegen targets this machine can run, for scripts/cpu_matrix.sh.

    python scripts/cpu_features.py missing haswell   # prints the instructions the host lacks ("" if none)
    python scripts/cpu_features.py host              # one line: the host CPU and its vector width

Reads the instruction-set flags of ``/proc/cpuinfo`` (Linux, x86-64); a target whose
flags are not all there would stop with an illegal instruction.
"""

from __future__ import annotations

import platform
import sys
from pathlib import Path

#: What each LLVM CPU name needs, as /proc/cpuinfo names the flags (the ones that matter
#: for vector code and that a lesser CPU lacks).
REQUIRED = {
    "x86-64": ("sse2",),
    "haswell": ("avx", "avx2", "fma", "bmi1", "bmi2", "movbe", "f16c"),
    "znver2": ("avx", "avx2", "fma", "bmi1", "bmi2", "movbe", "f16c", "sha_ni", "clzero", "clwb"),
    "znver3": ("avx", "avx2", "fma", "bmi1", "bmi2", "movbe", "f16c", "sha_ni", "clzero", "clwb", "vaes",
               "vpclmulqdq"),
    "skylake-avx512": ("avx2", "fma", "bmi2", "avx512f", "avx512dq", "avx512bw", "avx512vl", "avx512cd"),
    "icelake-server": ("avx2", "fma", "avx512f", "avx512dq", "avx512bw", "avx512vl", "avx512cd", "avx512vbmi",
                       "avx512_vnni", "gfni", "vaes"),
    "znver4": ("avx2", "fma", "avx512f", "avx512dq", "avx512bw", "avx512vl", "avx512cd", "avx512_bf16",
               "vaes", "vpclmulqdq"),
}


def host_flags() -> set[str]:
    """The host's instruction-set flags (empty when /proc/cpuinfo has none)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return set()
    for line in text.splitlines():
        if line.startswith("flags"):
            return set(line.split(":", 1)[1].split())
    return set()


def host_line() -> str:
    """``AMD EPYC (llvm: znver3), AVX2 only, 2 cores`` or the like."""
    import os

    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        import llvmlite.binding as ll

        llvm = ll.get_host_cpu_name()
    except Exception:  # noqa: BLE001 - only for the label
        llvm = "?"
    flags = host_flags()
    width = "AVX-512" if "avx512f" in flags else "AVX2 only" if "avx2" in flags else "no AVX2"
    return f"{model} (llvm: {llvm}), {width}, {os.cpu_count()} cores"


def main(argv: list[str]) -> int:
    if len(argv) == 1 and argv[0] == "host":
        print(host_line())
        return 0
    if len(argv) == 2 and argv[0] == "missing":
        target = argv[1]
        if target not in REQUIRED:
            print(f"unknown target {target!r}: one of {', '.join(REQUIRED)}", file=sys.stderr)
            return 2
        if platform.machine() not in ("x86_64", "AMD64"):
            print(f"an x86-64 target on a {platform.machine()} machine")
            return 0
        print(" ".join(f for f in REQUIRED[target] if f not in host_flags()))
        return 0
    print(__doc__, file=sys.stderr)
    return 2


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
