"""Which BLAS a benchmark runs on: library, version and the CPU kernels it chose."""

from __future__ import annotations

from threadpoolctl import threadpool_info


def describe() -> str:
    """One line, e.g. ``openblas 0.3.30 (SkylakeX kernels)``, for each BLAS loaded."""
    libs = sorted(
        {
            (d["internal_api"], str(d.get("version")), str(d.get("architecture")))
            for d in threadpool_info()
            if d["user_api"] == "blas"
        }
    )
    return ", ".join(f"{api} {version} ({arch} kernels)" for api, version, arch in libs)
