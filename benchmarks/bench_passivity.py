"""Issue 18, "show the need": a released haptic handle under delay, passivity controller off and on.

Runs :func:`teleop.passivity_sim.simulate_release` (the station's own eq. (15), eq. (16), device model and
passivity tick; the link and vehicle modelled) at one-way delays of 0, 100, 150 and 300 ms, for the
shipped gains and for a crisper device (low mechanism friction and damping B), and prints the RMS handle
velocity after the release and the port energy account. Then the same on a loaded machine (5 % of the
force loop's ticks last 2-20 ms, the force held over them): the H&R controller alone, and with the
passivity layer (Franken et al. 2011) behind it, the min observed energy against epsilon.
Saves a plot of handle position and force.

    python benchmarks/bench_passivity.py [--out passivity.png] [--vehicle-tau-s 0.05]
"""

from __future__ import annotations

import argparse
from dataclasses import replace

from teleop.config import DeviceConfig, ForceConfig, TeleopConfig
from teleop.passivity_sim import DelayedLoop, LoopRun, simulate_release

ONE_WAY_MS = (0.0, 100.0, 150.0, 300.0)
SETTLE_S = 1.0        # RMS velocity from this long after the release (the release transient itself excluded)
EPSILON_J = 1e-3     # harness/demo/report.py TARGETS["passivity_epsilon_j"]
LONG_TICKS = {"long_tick_probability": 0.05, "long_tick_max_s": 0.02}


def configs() -> dict[str, TeleopConfig]:
    return {
        "shipped (C 2, B 3 N s/m)": TeleopConfig(),
        "crisp (C 0.5, B 0.5 N s/m)": TeleopConfig(device=DeviceConfig(damping_n_s_m=(0.5, 0.5, 0.5)),
                                                   force=ForceConfig(B_n_s_m=(0.5, 0.5, 0.5))),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="bench_passivity.png", help="PNG of handle position and force")
    ap.add_argument("--vehicle-tau-s", type=float, default=0.05, help="vehicle velocity-loop time constant")
    ap.add_argument("--duration-s", type=float, default=8.0)
    args = ap.parse_args()
    base = DelayedLoop(vehicle_time_constant_s=args.vehicle_tau_s, duration_s=args.duration_s)
    print(f"released handle from q0 = {base.q0_m} m, vehicle lag {base.vehicle_time_constant_s} s, "
          f"feedback {base.feedback_rate_hz:g} Hz; RMS velocity from {SETTLE_S:g} s after release")
    print(f"{'gains':28s} {'one-way':>8s} {'PC':>4s} {'RMS v m/s':>10s} {'min E J':>10s} {'injected J':>11s} "
          f"{'dissipated J':>12s} {'|q| end m':>10s}")
    runs: dict[tuple[str, float, bool], LoopRun] = {}
    for name, cfg in configs().items():
        for one_way in ONE_WAY_MS:
            loop = replace(base, round_trip_s=2 * one_way * 1e-3)
            for on in (False, True):
                r = simulate_release(cfg, loop, on)
                runs[(name, one_way, on)] = r
                rep = r.report
                print(f"{name:28s} {one_way:6.0f}ms {'on' if on else 'off':>4s} {r.rms_velocity_m_s(SETTLE_S):10.4f} "
                      f"{rep.min_observed_j:10.4f} {rep.output_j:11.4f} {rep.dissipated_j:12.4f} "
                      f"{abs(r.q_x_m[-500:]).max():10.4f}")
    # a loaded machine: long ticks. H&R alone (its 1 ms prediction) against H&R + the passivity layer
    crisp = configs()["crisp (C 0.5, B 0.5 N s/m)"]
    hr_only = replace(crisp, passivity=replace(crisp.passivity, tank_layer=False))
    print(f"\nlong ticks ({LONG_TICKS['long_tick_probability']:.0%} of ticks last 2-"
          f"{LONG_TICKS['long_tick_max_s'] * 1e3:.0f} ms), crisp gains; min E against -epsilon = -{EPSILON_J} J")
    print(f"{'controller':28s} {'one-way':>8s} {'RMS v m/s':>10s} {'min E J':>10s} {'injected J':>11s} "
          f"{'dissipated J':>12s} {'|q| end m':>10s} {'min E >= -eps':>13s}")
    for one_way in (150.0, 300.0):
        loop = replace(base, round_trip_s=2 * one_way * 1e-3, **LONG_TICKS)  # type: ignore[arg-type]
        for name, cfg, on in (("off", crisp, False), ("H&R only", hr_only, True), ("H&R + layer", crisp, True)):
            r = simulate_release(cfg, loop, on)
            rep = r.report
            verdict = "" if not on else ("yes" if rep.min_observed_j >= -EPSILON_J else "NO")
            print(f"{name:28s} {one_way:6.0f}ms {r.rms_velocity_m_s(SETTLE_S):10.4f} {rep.min_observed_j:10.5f} "
                  f"{rep.output_j:11.4f} {rep.dissipated_j:12.4f} {abs(r.q_x_m[-500:]).max():10.4f} {verdict:>13s}")
    print()
    # the credit stored before the release lets the oscillation grow until it is spent: a tank ceiling
    for cap_j in (0.005, 0.001):
        capped = replace(crisp, passivity=replace(crisp.passivity, energy_cap_j=cap_j))
        r = simulate_release(capped, replace(base, round_trip_s=0.6), True)
        print(f"{'crisp, energy_cap_j ' + format(cap_j, 'g'):28s} {300:6.0f}ms {'on':>4s} "
              f"{r.rms_velocity_m_s(SETTLE_S):10.4f} {r.report.min_observed_j:10.4f} {r.report.output_j:11.4f} "
              f"{r.report.dissipated_j:12.4f} {abs(r.q_x_m[-500:]).max():10.4f}")
    print(f"target: with the controller on, min E >= -{EPSILON_J} J at every delay (with long ticks too); at "
          "300 ms one-way the RMS velocity is measurably lower than off")
    _plot(runs, args.out)


def _plot(runs: dict[tuple[str, float, bool], LoopRun], out: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    name = "crisp (C 0.5, B 0.5 N s/m)"
    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    for on, style in ((False, "r-"), (True, "b-")):
        r = runs[(name, 300.0, on)]
        label = f"300 ms one-way, controller {'on' if on else 'off'}"
        axes[0].plot(r.t_s, r.q_x_m * 1e3, style, lw=0.8, label=label)
        axes[1].plot(r.t_s, r.force_x_n, style, lw=0.8, label=label)
        axes[2].plot(r.t_s, r.energy_x_j, style, lw=0.8, label=label)
    r0 = runs[(name, 0.0, False)]
    axes[0].plot(r0.t_s, r0.q_x_m * 1e3, "k--", lw=0.8, label="no delay")
    axes[0].set_ylabel("handle q_x (mm)")
    axes[1].set_ylabel("force tau_x (N)")
    axes[2].set_ylabel("observed energy (J)")
    axes[2].set_yscale("symlog", linthresh=1e-3)
    axes[2].set_xlabel("time since release (s)")
    axes[0].set_title(f"Released handle, {name}: eq. (15) through a delayed link")
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    print(f"plot: {out}")


if __name__ == "__main__":
    main()
