"""End-to-end wall-clock of one weekly run: from scratch (no model cache) and with a cached model.

    python -m bench.e2e            # default preset (targets: scratch <= 15 min, cached <= 60 s)
    python -m bench.e2e --quick    # tiny preset, seconds

Runs the real ``weekly_forecast`` flow (Prefect ephemeral API) twice in one fresh temporary data
directory, importing the recorded DataSF exports (offline, so network time is not measured):
run 1 trains (scratch), run 2 reuses the trained model (cached). Writes bench/results/e2e.json.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

from pipeline.io import atomic_write_json

ROOT = Path(__file__).resolve().parents[1]
DATASF = ROOT.parent / "shared" / "data" / "datasf"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="tiny preset (smoke test)")
    parser.add_argument("--datasf", default=str(DATASF), help="folder of DataSF CSV exports")
    parser.add_argument("--out", default=str(ROOT / "bench" / "results" / "e2e.json"))
    args = parser.parse_args(argv)
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("DO_NOT_TRACK", "1")
    # Under load the ephemeral API can take longer than Prefect's default 20 s to come up.
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")
    preset = "tiny" if args.quick else "default"
    with tempfile.TemporaryDirectory(prefix="flowcast-e2e-") as tmp:
        os.environ["FLOWCAST_DATA_DIR"] = str(Path(tmp) / "data")
        from flows.weekly_forecast import weekly_forecast

        timings = {}
        for label, kwargs in [("scratch", {"data_source": "import",
                                            "import_from": [args.datasf]}),
                              ("cached", {"data_source": "cache"})]:
            start = time.perf_counter()
            result = weekly_forecast(preset=preset, output_dir=str(Path(tmp) / "reports"),
                                     **kwargs)
            timings[label] = time.perf_counter() - start
            expected_reuse = label == "cached"
            if result["model_reused"] != expected_reuse:
                raise SystemExit(f"{label} run: model_reused={result['model_reused']}")
    payload = {"preset": preset, "cached_seconds": round(timings["cached"], 2),
               "scratch_seconds": round(timings["scratch"], 2),
               "targets": {"cached_seconds": 60, "scratch_seconds": 900},
               "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
               "note": "wall-clock of the whole flow incl. Prefect ephemeral API start-up; data "
                       "imported from recorded DataSF exports (no network)"}
    atomic_write_json(args.out, payload)
    print(payload)
    return 0


if __name__ == "__main__":
    sys.exit(main())
