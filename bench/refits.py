"""nf-real's refits over the design rounds → ``refits`` of bench/results/replay.json.

Every refit date of the hub's design rounds (both targets: the refit calendar over their
vintages' last weeks, each refit on the vintage of its date, as the hub round fine-tunes) × 3
training seeds (the seed of the validation split, the synthetic windows drawn and the batches),
fine-tuned with the settings before issue 37 (no early stop, gradients clipped at norm 10) and
after (:class:`~pipeline.members.nf.real.FineTuneConfig`: stop after two evaluations
without improvement, best state kept, clipped at norm 1): how many diverged
(:class:`~pipeline.errors.TrainingDivergedError`), and each learning rate's mean best
validation NLL with the new settings (``lr``: the one with the lowest is the default).

    python -m bench.refits [--store DIR] [--seeds 0 1 2] [--lrs 2.5e-4 5e-4 1e-3]
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import tempfile
import time
from pathlib import Path
from typing import Any

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "nhsn"
BEFORE_LR = 5e-4


def _refit(flow: Any, cut: Any, config: Any) -> tuple[bool, float, int, str]:
    """(diverged, best validation NLL, iterations run, why) of one fine-tune."""
    from pipeline.errors import TrainingDivergedError
    from pipeline.training.trainer import train

    model = copy.deepcopy(flow.estimator)
    model.train()
    train_ds, val_ds = cut
    try:
        result = train(model, train_ds, val_ds, config.train_config())
    except TrainingDivergedError as error:
        return True, float("nan"), -1, str(error)
    return False, float(result.best_val_nll), int(result.iterations_run), result.stop_reason


def run_refits(store: Path | None = None, hub: Path = SHARED, seeds: tuple[int, ...] = (0, 1, 2),
               lrs: tuple[float, ...] = (2.5e-4, 5e-4, 1e-3)) -> dict[str, Any]:
    import pandas as pd

    from pipeline.data.hub.target_import import import_hub_time_series
    from pipeline.data.core.cache import data_folder
    from pipeline.hub_round.run import load_vintages
    from pipeline.members.nf.flow import SyntheticWindows, stored_flow
    from pipeline.members.nf.real import refit_windows
    from pipeline.members.nf.refit import refit_dates
    from pipeline.members.nf.weekly import WeeklyFlowMember
    from pipeline.members.published import HubMembersConfig
    from pipeline.panels.hub import ED_COVID, HOSP_COVID
    from pipeline.training.digests import DataDigests

    members = HubMembersConfig()
    after = members.finetune
    # the settings before issue 37: the trainer's defaults, the hub's lr then
    before = dataclasses.replace(after, early_stop_patience=None, grad_clip_norm=10.0,
                                 lr=BEFORE_LR)
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="flowcast-refits-") as tmp:
        with data_folder(Path(tmp) / "data"):
            import_hub_time_series(hub / "time-series.parquet")
            root = store or Path(tmp) / "data" / "models"
            synthetic = SyntheticWindows(members.flow, DataDigests(root))
            stored = stored_flow(members.flow, root, synthetic=synthetic)
            flow = WeeklyFlowMember(stored.estimator, members.flow, n_samples=100)
            rows = []
            for target in (HOSP_COVID, ED_COVID):
                vintages = load_vintages(target)
                dates = refit_dates(sorted({p.last_date for _, p in vintages}),
                                    after.refit_every_weeks)
                for date in dates:
                    known = [p for _, p in vintages if p.last_date <= date][-1]
                    cutoff = date - pd.Timedelta(days=after.revision_days)
                    for seed in seeds:
                        for label, config in (
                                ("before", before), ("after", after),
                                *((f"lr={lr:g}", dataclasses.replace(after, lr=lr))
                                  for lr in lrs if lr != after.lr)):
                            config = dataclasses.replace(config, seed=seed)
                            cut = refit_windows(flow, list(known.histories.values()), cutoff,
                                                synthetic, config)
                            if cut is None:
                                continue
                            diverged, nll, its, why = _refit(flow, cut, config)
                            rows.append({"target": target, "date": str(date.date()),
                                         "seed": seed, "settings": label, "lr": config.lr,
                                         "diverged": diverged, "best_val_nll": nll,
                                         "iterations": its, "stop": why})
                            print(json.dumps(rows[-1]), flush=True)
    frame = pd.DataFrame(rows)
    after_lr = frame[frame["settings"] != "before"]
    by_lr = after_lr.groupby("lr")["best_val_nll"].mean()
    return {
        "dates": sorted({f"{r['target']} {r['date']}" for r in rows}),
        "seeds": list(seeds),
        "diverged_before": int(frame[frame["settings"] == "before"]["diverged"].sum()),
        "diverged_after": int(frame[frame["settings"] == "after"]["diverged"].sum()),
        "refits_each": int((frame["settings"] == "after").sum()),
        "diverged_by_settings": {s: int(g["diverged"].sum())
                                 for s, g in frame.groupby("settings")},
        "rounds_lost_after": 0,   # a diverged refit falls back (pipeline.members.nf.real)
        "before_settings": {"early_stop_patience": None, "grad_clip_norm": 10.0,
                            "lr": BEFORE_LR},
        "after_settings": {"early_stop_patience": after.early_stop_patience,
                           "grad_clip_norm": after.grad_clip_norm, "lr": after.lr},
        "lr_mean_best_val_nll": {f"{lr:g}": float(v) for lr, v in by_lr.items()},
        "lr_chosen_by_measurement": float(by_lr.idxmin()),
        "iterations_mean": {s: float(g["iterations"].mean())
                            for s, g in frame[~frame["diverged"]].groupby("settings")},
        "seconds": round(time.perf_counter() - started, 1),
        "rows": rows,
    }


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--store", default=None, help="a model store holding the weekly flow")
    p.add_argument("--hub", default=str(SHARED))
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--lrs", type=float, nargs="+", default=[2.5e-4, 5e-4, 1e-3])
    p.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" /
                                        "replay.json"))
    args = p.parse_args(argv)
    from bench.replay import _merge

    result = run_refits(Path(args.store) if args.store else None, Path(args.hub),
                        tuple(args.seeds), tuple(args.lrs))
    _merge(Path(args.out), {"refits": result, "command_refits": "python -m bench.refits "
                            + " ".join(argv or [])})
    print({k: v for k, v in result.items() if k != "rows"})


if __name__ == "__main__":
    main()
