"""The online controller on the simulator: Table III-like statistics over seeds.

    python benchmarks/bench_controller.py               # ~1 min
    python benchmarks/bench_controller.py --seeds 50 --tasks 300 --json out.json

Sections:
* ``table3``: per deadline (5 / 7.5 / 10 s, the paper's Dance1 runs) and acceptance margin
  (0 and the paper's 1 s): search steps, chosen configuration against the noise-free optimum
  (same N' share, quality regret), mean time after convergence vs Δt, deadline misses.
* ``exact``: noise-free random models — the search finds the optimum within tau.
* ``adjust``: the minor adjustment's running average (paper: all tasks; ours: 5) and target.
* ``late``: ``late_share`` (a share of late tasks instead of an average at the deadline)
  under uniform and lognormal timing noise: late tasks after convergence, mean time error,
  quality.
* ``triggers``: load steps (x0.7, x1.4, x2) — re-search delay; false re-searches without one.
* ``real`` (not in the default set; minutes): the controller driving real reconstructions
  (``edgerecon.pipeline.reconstruct``, sparse + dense, whole scene) on a dataset such as
  utrecht4cam. Per task the golden configuration is reconstructed too (the back-end's job in
  the runtime) to give the online estimate (sparse vs golden sparse) and an offline score
  (dense vs golden dense); pi(N') comes from the golden sparse cloud of the first task.

    python benchmarks/bench_controller.py --section real --dataset ../shared/data/utrecht4cam \
        --deadline 3.5 --tasks 30
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
from collections.abc import Callable
from typing import Any

import numpy as np

from edgerecon.optimize import (
    BisectionController,
    ControllerConfig,
    PipelineModel,
    SimulatorConfig,
    run_simulation,
    true_optimum,
)

ROWS: list[dict[str, Any]] = []


def emit(section: str, **kw: Any) -> None:
    ROWS.append({"section": section, **kw})
    print(
        f"{section:9s} "
        + "  ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in kw.items()),
        flush=True,
    )


def table3(args: argparse.Namespace) -> None:
    sim = SimulatorConfig(time_noise=args.noise)
    model = PipelineModel(sim)
    for margin in (0.0, 1.0):
        for deadline in (5.0, 7.5, 10.0):
            cfg = ControllerConfig(deadline_s=deadline, margin_s=margin)
            opt = true_optimum(model, deadline)
            steps, same_n, regret, err, miss, conv, searches, scale, ncam = ([] for _ in range(9))
            for seed in range(args.seeds):
                res = run_simulation(deadline, args.tasks, seed=seed, simulator=sim, controller=cfg)
                s = res.summary
                steps.append(s.search_steps)
                searches.append(s.num_searches)
                if s.tasks_converged:
                    err.append(s.time_error)
                    miss.append(s.misses_converged / s.tasks_converged)
                    conv.append(s.tasks_converged)
                    scale.append(s.avg_scale)
                    ncam.append(s.num_cameras)
                    same_n.append(s.num_cameras == opt.num_cameras)
                    # regret of the converged configuration on the noise-free model
                    after = [r for r in res.rows if r.task >= (s.converged_task or 0)]
                    q = np.mean([model.quality(r.scale, r.num_cameras) for r in after])
                    regret.append(1 - q / opt.quality)
            emit(
                "table3",
                deadline_s=deadline,
                margin_s=margin,
                steps_mean=float(np.mean(steps)),
                steps_min=int(np.min(steps)),
                steps_max=int(np.max(steps)),
                opt=f"({opt.scale:.3f},{opt.num_cameras})",
                avg_scale=float(np.mean(scale)),
                cams_mode=int(np.bincount(ncam).argmax()),
                same_N_share=float(np.mean(same_n)),
                quality_regret_pct=100 * float(np.mean(regret)),
                time_err_pct_mean=100 * float(np.mean(err)),
                time_err_pct_max=100 * float(np.max(np.abs(err))),
                miss_pct_converged=100 * float(np.mean(miss)),
                searches_mean=float(np.mean(searches)),
            )


def exact(args: argparse.Namespace) -> None:
    rng = np.random.default_rng(0)
    ok = total = 0
    steps = []
    for _ in range(args.models):
        n = int(rng.integers(3, 13))
        sim = SimulatorConfig(
            num_cameras=n,
            base_s=float(rng.uniform(0, 3)),
            per_camera_s=float(rng.uniform(0.2, 2)),
            camera_exponent=float(rng.uniform(0.5, 1.8)),
            quality_scale_exponent=float(rng.uniform(0.2, 1.5)),
            quality_camera_exponent=float(rng.uniform(0, 1.5)),
            time_noise=0,
            quality_noise=0,
        )
        model = PipelineModel(sim)
        deadline = float(rng.uniform(model.time_s(0.3, 3), model.time_s(1.0, n) * 1.2))
        cfg = ControllerConfig(deadline_s=deadline)
        ctrl = BisectionController(cfg, {k: tuple(range(k)) for k in range(3, n + 1)}, n)
        for i in range(500):
            c = ctrl.next_config()
            t, q = model.sample(c.scale, c.num_cameras, i, rng)
            ctrl.observe(t, 1.0 if c.phase == "golden" else q)
            if ctrl.phase == "adjust":
                break
        opt = true_optimum(model, deadline, num_cameras=n)
        if not opt.feasible:
            continue
        total += 1
        steps.append(ctrl.search_steps)
        ch = ctrl.chosen
        floor = model.quality(max(0.3, opt.scale - cfg.tau), opt.num_cameras)
        ok += ch is not None and model.quality(ch.scale, ch.num_cameras) >= floor - 1e-12
    emit(
        "exact",
        feasible_models=total,
        optimum_within_tau=ok,
        steps_mean=float(np.mean(steps)),
        steps_max=int(np.max(steps)),
    )


def _converged(
    args: argparse.Namespace,
    controller: Callable[[float], ControllerConfig],
    simulator: SimulatorConfig,
) -> list[Any]:
    """The simulations at deadlines 5 / 7.5 / 10 s and ``args.seeds`` seeds that converged."""
    out = []
    for deadline in (5.0, 7.5, 10.0):
        cfg = controller(deadline)
        for seed in range(args.seeds):
            res = run_simulation(
                deadline, args.tasks, seed=seed, controller=cfg, simulator=simulator
            )
            if res.summary.tasks_converged:
                out.append(res)
    return out


def _late_share(res: Any) -> float:
    return res.summary.misses_converged / res.summary.tasks_converged


def adjust(args: argparse.Namespace) -> None:
    for window in (0, 5, 10):
        for target in (1.0, 0.9):
            runs = _converged(
                args,
                lambda d, w=window, a=target: ControllerConfig(
                    deadline_s=d, adjust_window=w, adjust_target=a
                ),
                SimulatorConfig(time_noise=args.noise),
            )
            err = [r.summary.time_error for r in runs]
            rstd = [np.std([x.scale for x in r.rows[-r.summary.tasks_converged :]]) for r in runs]
            emit(
                "adjust",
                window=window,
                target=target,
                time_err_pct_mean=100 * float(np.mean(err)),
                time_err_pct_max=100 * float(np.max(np.abs(err))),
                miss_pct=100 * float(np.mean([_late_share(r) for r in runs])),
                r_std=float(np.mean(rstd)),
            )


def triggers(args: argparse.Namespace) -> None:
    false = []
    for deadline in (5.0, 7.5, 10.0):
        for seed in range(args.seeds):
            res = run_simulation(
                deadline, args.tasks, seed=seed, simulator=SimulatorConfig(time_noise=args.noise)
            )
            false.append(sum(e["reason"] in ("drift", "slower") for e in res.events))
    emit(
        "triggers",
        load="x1 (none)",
        tasks=args.tasks * len(false),
        drift_or_slower_researches=int(np.sum(false)),
    )
    for factor in (0.7, 1.2, 1.4, 2.0):
        delays, errs = [], []
        for seed in range(args.seeds):
            sim = SimulatorConfig(time_noise=args.noise, load_steps=((100, factor),))
            res = run_simulation(7.5, max(args.tasks, 250), seed=seed, simulator=sim)
            ev = [e for e in res.events if e["task"] >= 100]
            delays.append(ev[0]["task"] - 100 if ev else -1)
            if res.summary.tasks_converged >= 20:
                errs.append(res.summary.time_error)
        detected = [d for d in delays if d >= 0]
        emit(
            "triggers",
            load=f"x{factor} at task 100",
            detected=f"{len(detected)}/{len(delays)}",
            delay_median=float(np.median(detected)) if detected else float("nan"),
            final_time_err_pct_max=100 * float(np.max(np.abs(errs))),
        )


def real(args: argparse.Namespace) -> None:
    import time

    from edgerecon.config import ReconstructionConfig
    from edgerecon.io.dataset import open_dataset
    from edgerecon.optimize import CameraSelector
    from edgerecon.pipeline import reconstruct
    from edgerecon.quality.online import (
        OnlineQualityConfig,
        online_offline_correlation,
        online_quality,
    )

    ds = open_dataset(args.dataset)
    rig = ds.rig
    n = len(rig)
    dirs = np.array([c.viewing_direction for c in rig])
    qcfg = OnlineQualityConfig(threshold_rel=args.threshold_rel)
    ctrl = BisectionController(ControllerConfig(deadline_s=args.deadline), None, n)
    rows = []
    with ds.open_frames() as frames:
        for task in range(args.tasks):
            index = args.start + task * args.step
            fs = frames.read(index)
            cfg = ctrl.next_config()
            t0 = time.perf_counter()
            golden = reconstruct(fs, rig, ReconstructionConfig())
            golden_s = time.perf_counter() - t0
            if cfg.phase == "golden":
                cand, seconds = golden, golden_s
                vis = golden.sparse.visibility_matrix(n)
                ctrl.set_camera_mapping(
                    CameraSelector(vis, camera_centers=rig.centers, viewing_directions=dirs)
                )
            else:
                t0 = time.perf_counter()
                cand = reconstruct(
                    fs, rig, ReconstructionConfig(scale=cfg.scale, camera_ids=cfg.camera_ids)
                )
                seconds = time.perf_counter() - t0
            online = online_quality(cand.sparse.cloud, golden.sparse.cloud, qcfg)
            offline = online_quality(cand.dense.cloud, golden.dense.cloud, qcfg)
            ctrl.observe(seconds, 1.0 if cfg.phase == "golden" else online.value)
            rows.append((task, index, cfg, seconds, golden_s, online.value, offline.value))
            emit(
                "real",
                task=task,
                frame=index,
                phase=cfg.phase,
                r=cfg.scale,
                cameras=",".join(map(str, cfg.camera_ids)),
                seconds=seconds,
                golden_seconds=golden_s,
                online_F=online.value if online.value is not None else float("nan"),
                offline_F=offline.value if offline.value is not None else float("nan"),
                sparse_points=cand.sparse.num_points,
            )
    adjust = [r for r in rows if r[2].phase == "adjust"]
    corr = online_offline_correlation([r[5] for r in rows[1:]], [r[6] for r in rows[1:]])
    emit(
        "real-sum",
        deadline_s=args.deadline,
        tasks=len(rows),
        search_steps=ctrl.total_search_steps,
        searches=ctrl.num_searches,
        chosen="-"
        if ctrl.chosen is None
        else f"({ctrl.chosen.scale:.3f},{ctrl.chosen.num_cameras})",
        adjust_tasks=len(adjust),
        avg_time_s=float(np.mean([r[3] for r in rows])),
        avg_time_adjust_s=float(np.mean([r[3] for r in adjust])) if adjust else float("nan"),
        avg_golden_s=float(np.mean([r[4] for r in rows])),
        misses_adjust=sum(r[3] > args.deadline for r in adjust),
        avg_online_F=float(np.nanmean([np.nan if r[5] is None else r[5] for r in rows[1:]])),
        avg_offline_F=float(np.nanmean([np.nan if r[6] is None else r[6] for r in rows[1:]])),
        corr_pearson=corr.pearson,
        corr_spearman=corr.spearman,
        corr_n=corr.num_samples,
        events=str(ctrl.events),
    )


def table4(args: argparse.Namespace) -> None:
    from edgerecon.config import ReconstructionConfig
    from edgerecon.io.dataset import open_dataset
    from edgerecon.pipeline import reconstruct
    from edgerecon.quality.online import (
        OnlineQualityConfig,
        online_offline_correlation,
        online_quality,
    )
    from edgerecon.types import FrameSet

    qcfg = OnlineQualityConfig(threshold_rel=args.threshold_rel)
    scales = [1.0, 0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3]
    frames_list = []
    truth: list[Any] = []
    if args.dataset.startswith("synthetic:"):
        from edgerecon.synth import Renderer, build_scene, preset_config
        from edgerecon.synth.groundtruth import rays_to_points
        from edgerecon.synth.render import pixel_grid_rays

        scene = build_scene(preset_config(args.dataset.split(":", 1)[1], seed=0))
        rig = scene.rig
        renderer = Renderer(scene)
        for k in range(args.frames):
            fr = renderer.render(10 + 7 * k)
            frames_list.append(FrameSet(time_index=fr.time_index, images=fr.images))
            pts = []
            for cam, depth in zip(rig, fr.depths, strict=True):
                xn, yn = pixel_grid_rays(cam)
                sl = (slice(None, None, 4), slice(None, None, 4))
                pts.append(rays_to_points(cam, xn[sl].ravel(), yn[sl].ravel(), depth[sl].ravel()))
            truth.append(np.concatenate(pts))
    else:
        ds = open_dataset(args.dataset)
        rig = ds.rig
        with ds.open_frames() as src:
            for k in range(args.frames):
                frames_list.append(src.read(args.start + k * 40))
    all_on, all_off, all_gt = [], [], []
    for k, fs in enumerate(frames_list):
        golden = reconstruct(fs, rig, ReconstructionConfig())
        on_f, off_f, gt_f = [], [], []
        for r in scales:
            res = golden if r == 1.0 else reconstruct(fs, rig, ReconstructionConfig(scale=r))
            on = online_quality(res.sparse.cloud, golden.sparse.cloud, qcfg).value
            off = online_quality(res.dense.cloud, golden.dense.cloud, qcfg).value
            gt = online_quality(res.dense.cloud, truth[k], qcfg).value if truth else None
            on_f.append(on)
            off_f.append(off)
            gt_f.append(gt)
            emit(
                "table4",
                frame=fs.time_index,
                r=r,
                sparse_points=res.sparse.num_points,
                online_F=np.nan if on is None else on,
                offline_F=np.nan if off is None else off,
                dense_vs_truth_F=np.nan if gt is None else gt,
            )
        c = online_offline_correlation(on_f, off_f)
        emit(
            "table4-c",
            frame=fs.time_index,
            vs="golden dense",
            pearson=c.pearson,
            spearman=c.spearman,
            trend=c.trend_agreement,
        )
        if truth:
            c = online_offline_correlation(on_f, gt_f)
            emit(
                "table4-c",
                frame=fs.time_index,
                vs="truth",
                pearson=c.pearson,
                spearman=c.spearman,
                trend=c.trend_agreement,
            )
        all_on += on_f
        all_off += off_f
        all_gt += gt_f
    c = online_offline_correlation(all_on, all_off)
    emit(
        "table4-c",
        frame="all",
        vs="golden dense",
        pearson=c.pearson,
        spearman=c.spearman,
        trend=c.trend_agreement,
        n=c.num_samples,
    )
    if truth:
        c = online_offline_correlation(all_on, all_gt)
        emit(
            "table4-c",
            frame="all",
            vs="truth",
            pearson=c.pearson,
            spearman=c.spearman,
            trend=c.trend_agreement,
            n=c.num_samples,
        )


def late(args: argparse.Namespace) -> None:
    for kind, noise in (("uniform", args.noise), ("lognormal", args.noise * 2 / 3)):
        for share, target in ((None, 1.0), (None, 0.95), (0.2, 1.0), (0.1, 1.0), (0.05, 1.0)):
            runs = _converged(
                args,
                lambda d, p=share, a=target: ControllerConfig(
                    deadline_s=d, adjust_target=a, late_share=p
                ),
                SimulatorConfig(time_noise=noise, noise_kind=kind),
            )
            miss = [_late_share(r) for r in runs]
            emit(
                "late",
                noise=f"{kind} {noise:g}",
                late_share=share,
                target=target,
                time_err_pct_mean=100 * float(np.mean([r.summary.time_error for r in runs])),
                late_pct=100 * float(np.mean(miss)),
                late_pct_p90=100 * float(np.percentile(miss, 90)),
                quality=float(np.mean([r.summary.avg_quality_converged for r in runs])),
            )


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--section", nargs="+", default=["table3", "exact", "adjust", "late", "triggers"]
    )
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--tasks", type=int, default=200)
    ap.add_argument("--models", type=int, default=500, help="random models in 'exact'")
    ap.add_argument("--noise", type=float, default=0.15)
    ap.add_argument("--dataset", help="dataset folder for the 'real' section")
    ap.add_argument("--deadline", type=float, default=3.5, help="'real': deadline (s)")
    ap.add_argument("--start", type=int, default=100, help="'real': first frame")
    ap.add_argument("--step", type=int, default=5, help="'real': frames between tasks")
    ap.add_argument(
        "--threshold-rel",
        type=float,
        default=0.01,
        help="'real': F-score threshold, share of the golden bbox diagonal",
    )
    ap.add_argument("--frames", type=int, default=3, help="'table4': frames to sweep")
    ap.add_argument("--json")
    args = ap.parse_args()
    sections = {
        "table3": table3,
        "exact": exact,
        "adjust": adjust,
        "triggers": triggers,
        "late": late,
        "real": real,
        "table4": table4,
    }
    for name in args.section:
        sections[name](args)
    if args.json:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=False
        ).stdout.strip()
        with open(args.json, "w") as f:
            json.dump(
                {
                    "commit": commit,
                    "python": sys.version,
                    "machine": platform.machine(),
                    "numpy": np.__version__,
                    "args": vars(args),
                    "rows": ROWS,
                },
                f,
                indent=1,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
