"""Benchmark: scoring every image-space candidate of ``plan`` for the three cameras of issue 10.

Run by hand:  .venv/bin/python benchmarks/bench_plan.py [--trials 200] [--baseline 12]

For each camera (the wide 1080p, the 4K, the paper's Table 1 distorted one,
planned from nominal values) it times ``plan.strategies.score_image_candidates``
(design + route timing + linearised ROI prediction + extrapolation term for
every candidate), and as the baseline measured in the same run the paper's
Monte-Carlo (``core.uncertainty.monte_carlo``, ``--trials``) of the first
``--baseline`` candidates' samples (thinned like ``plan`` does, to 800 points),
extrapolated to all candidates. Prints seconds, candidates/s and the ratio,
then the chosen plan's figures and paper-far's, as ``plan`` prints them.

``--check N`` adds a synthetic check of the prediction: the truth camera is
the guess with issue 10's *true* lens; the chosen plan's samples are observed
with the prediction's noise (2 px, RTK 1 / 1.5 cm, shared along 5 s of a leg,
timing 0.01 s), calibrated by ``core.calibrate.calibrate`` with the
prediction's model, N seeds; the error against the truth is measured over
the ROI points and over the ground 3-30 m, beside the prediction (ratio
measured / predicted: above 1 the prediction was optimistic).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from dronecal_field.core.uncertainty import monte_carlo
from dronecal_field.plan.route import FlightModel
from dronecal_field.plan.site import resolve_options
from dronecal_field.plan.stage import make_plan, request_from_options
from dronecal_field.plan.strategies import image_candidate_params, score_image_candidates
from dronecal_field.sampling.design import SAMPLINGS
from dronecal_field.sampling.predict import NoiseModel, lens_draws, normalised_radius, sample_sigmas
from dronecal_field.sampling.roi import build_roi, evaluation_points
from dronecal_field.plan.site import guess_camera

SITE = dict(lat=-35.363261, lon=149.165230, ground_alt=584.0, azimuth=90.0)
CAMERAS = {
    "a wide 1080p": dict(image_size="1920x1080", focal_px=900, mount_height=3.5, tilt=25, distortion="strong"),
    "b 4K": dict(image_size="3840x2160", focal_px=2600, mount_height=4.5, tilt=35, distortion="medium"),
    "c paper Table 1": dict(image_size="1280x960", focal_px=1110, mount_height=2.0, tilt=30, distortion="medium"),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--trials", type=int, default=200, help="Monte-Carlo trials of the baseline (plan's default)")
    parser.add_argument("--baseline", type=int, default=12, help="candidates scored by Monte-Carlo for the baseline")
    parser.add_argument("--check", type=int, default=0, metavar="N", help="synthetic check of the chosen plans' prediction with N seeds")
    parser.add_argument("--check-sigma-px", type=float, default=2.0, metavar="PX",
                        help="pixel noise of the synthetic check and of its plans' prediction (2 = the paper's; a hold's mean of 40 frames is nearer 0.3)")
    args = parser.parse_args()

    total_lin, total_mc, total_n, total_cpu = 0.0, 0.0, 0, 0.0
    reports = []
    checks = []
    for name, cam in CAMERAS.items():
        req = request_from_options(resolve_options({**SITE, **cam, "trials": args.trials, "sigma_px": args.check_sigma_px}))
        camera = guess_camera(req.site, req.lens, frame="site")
        roi = build_roi(camera, req.roi)
        pts, _ = evaluation_points(roi)
        noise = NoiseModel()
        draws = lens_draws(camera, camera.distortion.as_array(), float(normalised_radius(camera, pts).max()))
        params = image_candidate_params(req.marker_sizes_m, SAMPLINGS)
        score_image_candidates(camera, roi, params[:2], req.limits, req.flight, req.timing, noise, draws)  # warm the compiled kernels
        t, c0 = time.perf_counter(), time.process_time()
        cands = score_image_candidates(camera, roi, params, req.limits, FlightModel(hover_s=req.flight.hover_s), req.timing, noise, draws)
        t_lin, cpu = time.perf_counter() - t, time.process_time() - c0
        total_cpu += cpu
        usable = [c for c in cands if c.usable][: args.baseline]
        t = time.perf_counter()
        for c in usable:
            d = c.design
            idx = np.arange(len(d.samples_site))
            if len(idx) > 800:
                idx = idx[np.linspace(0, len(idx) - 1, 800).round().astype(int)]
            s3 = sample_sigmas(d.samples_sigma_h_m[idx], noise, d.samples_rtk_factor[idx])
            monte_carlo(camera, d.samples_site[idx], trials=args.trials, sigma_3d=s3, sigma_2d=2.0, model=c.prediction.model)
        t_mc = (time.perf_counter() - t) / max(len(usable), 1) * len(cands)
        total_lin += t_lin
        total_mc += t_mc
        total_n += len(cands)
        print(f"{name:<16} {len(cands):>4} candidates: linearised + extrapolation {t_lin:6.2f} s wall, {cpu:6.2f} s CPU ({len(cands) / t_lin:6.1f}/s); "
              f"Monte-Carlo {args.trials} trials (from {len(usable)}) {t_mc:7.1f} s; ratio {t_mc / t_lin:5.1f}x")
        t = time.perf_counter()
        result = make_plan(req)
        reports.append((name, result.summary, time.perf_counter() - t))
        if args.check:
            checks.append((name, synthetic_check(result, TRUE_LENS[name], args.check, args.check_sigma_px)))
    print(f"{'all three':<16} {total_n:>4} candidates: {total_lin:6.2f} s wall, {total_cpu:.2f} s CPU ({total_n / total_lin:.1f}/s); "
          f"Monte-Carlo {total_mc:.1f} s; ratio {total_mc / total_lin:.1f}x")
    print()
    print(f"{'camera':<16} {'plan':<36} {'cover':>5} {'holds':>5} {'pass':>5} {'legpts':>6} {'flight':>6} {'lin':>6} {'extrap':>6} {'comb':>6} {'gnd cm':>6}")
    for name, s, dt in reports:
        p, f, smp = s["prediction"], s["flight"], s["samples"]
        print(f"{name:<16} {s['strategy']['name']:<36} {s['coverage']['pct']:>5.0f} {smp['holds']:>5} {smp['pass_through_points']:>5} {smp['leg_samples']:>6} "
              f"{f['flight_time_s'] / 60:>6.1f} {p['linearised_px']['rms']:>6.2f} {p['extrapolation_px']['rms']:>6.2f} {p['combined_px']['rms']:>6.2f} "
              f"{p['ground_combined_cm']['rms']:>6.1f}   ({f['n_flights']} flight(s); make_plan {dt:.1f} s)")
        c = s["comparison"]
        cp = c.get("prediction")
        if cp:
            print(f"{'':<16} {'paper-far ' + c['strategy']:<36} {c['coverage_pct']:>5.0f} {c['points']:>5} {0:>5} {0:>6} "
                  f"{(c.get('flight_time_s') or float('nan')) / 60:>6.1f} {cp['linearised_px']['rms']:>6.2f} {cp['extrapolation_px']['rms']:>6.2f} "
                  f"{cp['combined_px']['rms']:>6.2f} {cp['ground_combined_cm']['rms']:>6.1f}")

    if checks:
        print()
        print(f"synthetic check ({args.check} seeds; truth = the guess with the true lens; noise {args.check_sigma_px:g} px, RTK 1 / 1.5 cm):")
        print(f"{'camera':<16} {'model':<9} {'ROI predicted':>13} {'ROI measured':>12} {'ratio':>6} {'ground 3-30 m RMS':>18} {'max':>7}")
        for name, c in checks:
            print(f"{name:<16} {c['model']:<9} {c['predicted_px']:>13.2f} {c['measured_px']:>12.2f} {c['measured_px'] / c['predicted_px']:>6.2f} "
                  f"{c['ground_rms_px']:>18.2f} {c['ground_max_px']:>7.1f}")


TRUE_LENS = {  # k1, k2, p1, p2, k3 of issue 10's truth cameras
    "a wide 1080p": (-0.28, 0.07, 0.0, 0.0, 0.0),
    "b 4K": (-0.32, 0.12, 4e-4, -3e-4, -0.02),
    "c paper Table 1": (-0.25, 0.0, -28e-5, -5e-5, 0.0),
}


def synthetic_check(result, lens: tuple[float, ...], seeds: int, sigma_px: float = 2.0) -> dict:
    """Calibrate the chosen plan's samples seen through the true lens with the prediction's noise; errors against the truth."""
    from dronecal_field.core.calibrate import calibrate
    from dronecal_field.core.camera import Distortion, intersect_plane_z
    from dronecal_field.sampling.design import RTK_CORRELATION_S
    from dronecal_field.sampling.roi import evaluation_points

    guess = result.camera_site
    truth = guess.with_(distortion=Distortion.from_array(np.array(lens)))
    chosen = result.chosen
    S, sig_t = chosen.samples_site, chosen.samples_sigma_h_m
    is_leg = sig_t > 0
    model = result.roi_prediction.model
    roi_pts, _ = evaluation_points(result.roi)
    # the visible ground 3-30 m: a grid of pixels whose true rays meet the ground there
    u = np.linspace(0.02, 0.98, 40) * (truth.width - 1)
    v = np.linspace(0.02, 0.98, 24) * (truth.height - 1)
    uv = np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)
    g = intersect_plane_z(*truth.batch_arrays(), uv[None], 0.0)[0]
    r = np.hypot(g[:, 0], g[:, 1])
    ground = g[np.isfinite(r) & (r >= 3.0) & (r <= 30.0)]
    gnss_hz = result.request.timing.gnss_hz
    chunk = max(1, int(gnss_hz * RTK_CORRELATION_S))
    roi_err, g_err = [], []
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        noise3 = rng.standard_normal((len(S), 3)) * np.array([0.01, 0.01, 0.015])
        legs = np.flatnonzero(is_leg)
        for start in range(0, len(legs), chunk):  # RTK error shared by the fixes of 5 s
            noise3[legs[start : start + chunk]] = rng.standard_normal(3) * np.array([0.01, 0.01, 0.015])
        noise3[:, :2] += rng.standard_normal((len(S), 2)) * sig_t[:, None] / np.sqrt(2.0)
        pix = truth.project(S) + rng.standard_normal((len(S), 2)) * sigma_px
        try:
            est = calibrate(S + noise3, pix, truth.width, truth.height, model=model if model != "default" else "k1k2p1p2", initial=guess).camera
        except Exception:
            continue
        roi_err.append(np.sum((est.project(roi_pts) - truth.project(roi_pts)) ** 2, axis=1))
        g_err.append(np.sum((est.project(ground) - truth.project(ground)) ** 2, axis=1))
    roi_e, g_e = np.concatenate(roi_err), np.concatenate(g_err)
    return {"model": model, "predicted_px": result.roi_prediction.combined_rms_px, "measured_px": float(np.sqrt(np.mean(roi_e))),
            "ground_rms_px": float(np.sqrt(np.mean(g_e))), "ground_max_px": float(np.sqrt(np.max(g_e)))}


if __name__ == "__main__":
    main()
