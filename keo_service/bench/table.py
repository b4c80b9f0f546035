"""The bench's results as the README's table, and as JSON."""

from __future__ import annotations

from typing import Any

import msgspec

from keo_service.bench.end_to_end import spread_of, value_at


def _spread(hp: dict[str, Any]) -> str:
    if "repeats" not in hp:
        return ""
    return (
        f" (median of {hp['repeats']} passes; best {hp['samples_per_s_best']:,.0f}, "
        f"worst {hp['samples_per_s_worst']:,.0f})"
    )


def _over_floor(hp: dict[str, Any], floor: dict[str, Any]) -> str:
    if "over_floor" not in hp:  # runs before the passes alternated
        return f"{hp['samples_per_s'] / floor['samples_per_s']:.2f}"
    return (
        f"{hp['over_floor']:.2f} (median of {hp['repeats']} alternating pairs; "
        f"{hp['over_floor_worst']:.2f} to {hp['over_floor_best']:.2f})"
    )


def _rerun_row(hp: dict[str, Any], hpr: dict[str, Any]) -> str:
    cost = (
        f"{hpr['samples_per_s']:,.0f} (x{hp['samples_per_s'] / hpr['samples_per_s']:.2f} the cost)"
    )
    if hpr.get("rerun") != "process":  # runs from before: the sink in the same thread
        return f"| hot path with the Rerun sink in the same thread | {cost} |"
    return (
        "| hot path with `--rrd`'s Rerun worker (each estimate encoded and piped to the Rerun "
        f"process; that process's own CPU: the end-to-end `--rrd` run below) | {cost} |"
    )


def _runs(command: dict[str, Any]) -> str:
    walls = command.get("runs_wall_s", [])
    if len(walls) < 2:
        return ""
    warmup = command.get("warmup_wall_s")
    after = "" if warmup is None else f" after a warm-up run of {warmup:.2f} s"
    return f" (median of {len(walls)} runs{after}, {min(walls):.2f} to {max(walls):.2f} s wall)"


def _floor_wall(rec: dict[str, Any]) -> str:
    """The floor's wall time, and the command's wall over the floor's CPU (the measure of
    runs before the floor's wall was taken), when the run has them."""
    if "floor_wall_s" not in rec:
        return ""
    return (
        f", {rec['floor_wall_s']:.2f} s wall (command wall / floor CPU "
        f"{rec['over_floor_wall_over_cpu']:.2f})"
    )


def _command_over_floor(rec: dict[str, Any]) -> str:
    b = rec["batch"]
    if "over_floor" not in rec:  # runs before the floor passes alternated with the command
        return f"{b['wall_s'] / rec['floor_s']:.2f}"
    return (
        f"{rec['over_floor']:.2f} (median of {len(b['runs_wall_s'])} pairs of a floor pass "
        f"and a command run; {rec['over_floor_best']:.2f} to {rec['over_floor_worst']:.2f})"
    )


def _ratio(spread: dict[str, Any] | None) -> str:
    if spread is None:
        return "not measured"
    each = ", ".join(f"{v:.2f}" for v in spread["each"])
    if len(spread["each"]) == 1:
        return f"x{each}"
    return f"x{spread['median']:.2f} (median; each round: {each})"


def _round_rows(r: dict[str, Any]) -> list[str]:
    rounds, ratios = r["end_to_end_rounds"], r["round_ratios"]
    n = len(rounds)
    label = (
        "same run"
        if n == 1
        else f"{n} rounds of the runs above, each ratio within its round, the order rotated"
    )
    lines = [
        f"| keo over the transport floor, {label} | "
        f"CPU {_ratio(ratios.get('service_cpu_over_relay'))}; "
        f"p50 {_ratio(ratios.get('p50_over_relay'))}; p99 {_ratio(ratios.get('p99_over_relay'))} |"
    ]
    if "math_cpu_over_relay" in ratios:
        lines += [
            "| the naive floor's math in the relay (per tracker pose: forward kinematics at "
            "the newest joints, the error transform and its log; what any estimator here "
            f"does) over the transport floor | CPU {_ratio(ratios['math_cpu_over_relay'])}; "
            f"p99 {_ratio(ratios.get('math_p99_over_relay'))} |",
            f"| keo over that naive math floor | CPU "
            f"{_ratio(ratios.get('service_cpu_over_math'))}; "
            f"p99 {_ratio(ratios.get('p99_over_math'))} |",
        ]
    less_fits = _cpu_less_fits_over_relay(rounds)
    if less_fits is not None:
        lines.append(
            "| keo's CPU without its delay fits (the worker's CPU time, counted by the "
            f"service) over the transport floor | {_ratio(less_fits)} |"
        )
    if n > 1:
        names = {
            "end_to_end": "service",
            "transport_floor": "relay",
            "end_to_end_rerun": "--rrd",
            "end_to_end_correction": "with correction",
            "math_floor": "naive math",
        }

        def each_run(path: tuple[str, ...], digits: int) -> str:
            """A value of every run, kind by kind (a p99 of no samples is None: nan)."""
            values = {k: [value_at(x[k], path) for x in rounds] for k in names if k in rounds[0]}
            return "; ".join(
                f"{names[k]} "
                + ", ".join(f"{float('nan') if v is None else v:.{digits}f}" for v in vs)
                for k, vs in values.items()
            )

        lines.append(f"| p99 in each round (ms) | {each_run(('latency_ms', 'p99'), 2)} |")
        if all("machine" in x[kind] for x in rounds for kind in names if kind in x):
            lines.append(
                "| CPU time the hypervisor took in each run (% of all cores) | "
                f"{each_run(('machine', 'steal_pct'), 1)} |"
            )
    if "correction_cpu_over_relay" in ratios:
        lines += _correction_rows(rounds, ratios)
    if "rrd_p99_over_plain" in ratios:
        drops = [x["end_to_end_rerun"].get("rerun_dropped", 0) for x in rounds]
        lines.append(
            f"| --rrd over the plain run, {'same bench' if n == 1 else f'{n} rounds'} | "
            f"p50 {_ratio(ratios.get('rrd_p50_over_plain'))}; "
            f"p99 {_ratio(ratios['rrd_p99_over_plain'])}; Rerun queue drops "
            f"{sum(drops)} |"
        )
    return lines


def _cpu_less_fits_over_relay(rounds: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The service's CPU less its delay fits' (`delay_fit_cpu_ms`, over the run's data) over
    the relay's, round by round; None for runs that did not count the fits."""
    values = []
    for x in rounds:
        run, relay = x.get("end_to_end"), x.get("transport_floor")
        if run is None or relay is None or not relay["processes"]["service"]["cpu_pct"]:
            continue
        fits_ms = run.get("service_counters", {}).get("delay_fit_cpu_ms")
        if fits_ms is None:
            continue
        own = run["processes"]["service"]["cpu_pct"] - 100.0 * fits_ms * 1e-3 / run["seconds"]
        values.append(own / relay["processes"]["service"]["cpu_pct"])
    return spread_of(values) if values else None


# the controller cycles a live correction feeds (ms): KUKA RSI and ABB EGM 4 ms, UR RTDE 2 ms
# (500 Hz, e-Series)
PROTOCOL_CYCLES_MS = {"RSI/EGM": 4.0, "RTDE": 2.0}


def _correction_rows(rounds: list[dict[str, Any]], ratios: dict[str, Any]) -> list[str]:
    """The correction path (the service with a correction output): its latency against the
    cycles it feeds, and its CPU and p99 against the relay of the same round."""
    runs = [x["end_to_end_correction"] for x in rounds if "end_to_end_correction" in x]
    lat = [x.get("correction_latency_ms", {}) for x in runs]
    p50 = [v["p50"] for v in lat if v.get("p50") is not None]
    p99 = [v["p99"] for v in lat if v.get("p99") is not None]
    if not p99:
        return ["| correction path latency | no correction arrived |"]
    worst = max(p99)
    within = ", ".join(
        f"{name} {cycle:g} ms: {'within' if worst <= cycle else 'NOT within'} at p99"
        for name, cycle in PROTOCOL_CYCLES_MS.items()
    )
    return [
        f"| correction path: tracker line -> correction at a subscriber (service with "
        f"`robot.correction` set; each round) | p50 {', '.join(f'{v:.2f}' for v in p50)} ms; "
        f"p99 {', '.join(f'{v:.2f}' for v in p99)} ms; against the cycles it feeds: {within} |",
        f"| service with a correction output over the transport floor, {len(runs)} rounds | "
        f"CPU {_ratio(ratios.get('correction_cpu_over_relay'))}; "
        f"p99 {_ratio(ratios.get('correction_p99_over_relay'))} |",
    ]


def _hot_path_rows(r: dict[str, Any]) -> list[str]:
    """The hot path against the naive floor, and with Rerun's worker."""
    hp, hpr = r["hot_path"], r["hot_path_rerun"]
    return [
        f"| hot path: aligned samples/s, one core{_spread(hp)} | {hp['samples_per_s']:,.0f} "
        f"({hp['us_per_sample']:.1f} us each; a 1 kHz tracker costs "
        f"{hp['core_share_at_1kHz_pct']:.1f} % of a core) |",
        f"| naive per-sample floor (FK, two SE3 products, log3; same run) | "
        f"{r['naive_floor']['samples_per_s']:,.0f} ({r['naive_floor']['us_per_sample']:.1f} us "
        f"each); hot path / floor = {_over_floor(hp, r['naive_floor'])} |"
        if "naive_floor" in r
        else "| naive per-sample floor | not measured in this run |",
        _rerun_row(hp, hpr),
    ]


def _recording_rows(rec: dict[str, Any]) -> list[str]:
    """The offline commands over the bench's recording: estimate (batch and streaming),
    calibrate-delay, analyze."""
    b = rec["batch"]
    lines = [
        f"| keo estimate, {rec['seconds']:.0f} s at 1 kHz ({rec['tracker_samples']:,} tracker, "
        f"{rec['encoder_samples']:,} encoder rows; CSV in and out, process start included) | "
        f"{b['wall_s']:.2f} s wall, {b['cpu_s']:.2f} s CPU, "
        f"peak RSS {b['peak_rss_mb']:.0f} MB{_runs(b)}; "
        f"naive floor over the same samples {rec['floor_s']:.2f} s CPU{_floor_wall(rec)}; "
        f"command / floor = {_command_over_floor(rec)} "
        f"({'wall over wall' if 'floor_wall_s' in rec else 'wall'}), "
        f"{b['cpu_s'] / rec['floor_s']:.2f} (CPU) |"
    ]
    if "streaming" in rec:
        st = rec["streaming"]
        lines.append(
            f"| keo estimate --streaming (per-sample path), same files | {st['wall_s']:.2f} s "
            f"wall, {st['cpu_s']:.2f} s CPU, peak RSS {st['peak_rss_mb']:.0f} MB; batch is "
            f"x{st['wall_s'] / b['wall_s']:.1f} faster |"
        )
    if "calibrate_delay" in rec:
        cd = rec["calibrate_delay"]
        lines.append(
            f"| keo calibrate-delay, same files (delay and drift, Gauss-Newton to 0.1 us) | "
            f"{cd['wall_s']:.2f} s wall, {cd['cpu_s']:.2f} s CPU, "
            f"peak RSS {cd['peak_rss_mb']:.0f} MB |"
        )
    if "analyze" in rec:
        an = rec["analyze"]
        lines.append(
            f"| keo analyze, the first {an['seconds']:.0f} s of the same files "
            f"({an['poses']:,} poses; registration, then every candidate effect fitted and "
            f"judged on held-out poses) | {an['wall_s']:.1f} s wall, {an['cpu_s']:.1f} s CPU, "
            f"peak RSS {an['peak_rss_mb']:.0f} MB |"
        )
    if "analyze_long" in rec:
        al = rec["analyze_long"]
        used = al["samples"].get("used", rec["tracker_samples"])
        lines.append(
            f"| keo analyze, the whole {rec['seconds']:.0f} s ({rec['tracker_samples']:,} "
            f"tracker samples, {used:,} informative ones used; held out "
            f"{al['held_out_pos_rms_mm']:.3f} mm) | {al['wall_s']:.1f} s wall, "
            f"{al['cpu_s']:.1f} s CPU, peak RSS {al['peak_rss_mb']:.0f} MB; command / floor "
            f"= {al['over_floor']:.0f} (wall) |"
        )
    return lines


def _ms(d: dict[str, float | None]) -> str:
    return ", ".join(f"{k} {v:.2f} ms" for k, v in d.items() if v is not None)


# the end-to-end kinds, in the table's order, and their rows' names
E2E_ROWS = (
    ("end_to_end", "end to end"),
    ("transport_floor", "transport floor (pass-through relay in the service's place)"),
    ("end_to_end_rerun", "end to end, --rrd"),
    ("end_to_end_correction", "end to end with a correction output"),
    ("math_floor", "naive math floor (the relay with the floor's math per tracker pose)"),
)


def _run_rows(e: dict[str, Any], label: str) -> list[str]:
    """One end-to-end run: its latency, the split at the service's publish, each process;
    the service's delay fits (its worker process) where the run counted them."""
    lines = [
        f"| {label}: tracker {e['tracker_hz']:.0f} Hz, robot {e['encoder_hz']:.0f} Hz, "
        f"{e['seconds']:.0f} s | latency {_ms(e['latency_ms'])}; "
        f"{e['estimates_received']} estimates for {e['tracker_samples_sent']} samples"
        + (
            f"; the machine {e['machine']['busy_pct']:.0f} % busy, "
            f"{e['machine']['steal_pct']:.1f} % stolen |"
            if "machine" in e
            else " |"
        )
    ]
    if "latency_to_service_publish_ms" in e:
        lines.append(
            f"| {label}: tracker line -> service publish / publish -> subscriber | "
            f"{_ms(e['latency_to_service_publish_ms'])} / "
            f"{_ms(e['latency_publish_to_subscriber_ms'])} |"
        )
    for name, p in e["processes"].items():
        own = f" (its own process {p['own_cpu_pct']:.1f} %)" if "own_cpu_pct" in p else ""
        if "threads_cpu_pct" in p:  # the service's (or the relay's) threads, by kind
            t = p["threads_cpu_pct"]
            own += (
                f"; its event loop's thread {t['event_loop']:.1f} %, other Python threads "
                f"(Zenoh's callbacks) {t['python_threads']:.1f} %, Zenoh's native threads "
                f"{t['native_threads']:.1f} %"
            )
        lines.append(
            f"| {label}: {name} | CPU {p['cpu_pct']:.1f} %{own}, peak RSS "
            f"{p['peak_rss_mb']:.0f} MB, RSS growth after warm-up "
            f"{p['rss_growth_mb']:+.1f} MB |"
        )
    fits_ms = e.get("service_counters", {}).get("delay_fit_cpu_ms")
    if fits_ms is not None:  # the fits happen while data flows: over the run's length
        lines.append(
            f"| {label}: the service's delay fits (its worker process; in its CPU above) | "
            f"{100.0 * fits_ms * 1e-3 / e['seconds']:.1f} % of a core over the "
            f"{e['seconds']:.0f} s of data |"
        )
    return lines


def _end_to_end_rows(r: dict[str, Any]) -> list[str]:
    """The end-to-end runs (round 1 of several), then the ratios of every round (or, in
    runs from before rounds, of the one pair)."""
    lines = []
    first_of = len(r.get("end_to_end_rounds", []))
    for key, kind in E2E_ROWS:
        if key in r:
            lines += _run_rows(r[key], kind + (f" (round 1 of {first_of})" if first_of > 1 else ""))
    if "round_ratios" in r:
        lines += _round_rows(r)
    elif "transport_floor" in r:  # runs before rounds: the one pair
        keo, floor = r["end_to_end"]["latency_ms"], r["transport_floor"]["latency_ms"]
        if keo["p99"] and floor["p99"]:
            lines.append(
                f"| keo over the transport floor, same run | p50 x{keo['p50'] / floor['p50']:.2f}, "
                f"p99 x{keo['p99'] / floor['p99']:.2f} |"
            )
    if "end_to_end_rerun" in r and "round_ratios" not in r:
        plain, rrd = r["end_to_end"]["latency_ms"], r["end_to_end_rerun"]["latency_ms"]
        if plain["p99"] and rrd["p99"]:
            lines.append(
                f"| --rrd over the plain run, same bench | p50 x{rrd['p50'] / plain['p50']:.2f}, "
                f"p99 x{rrd['p99'] / plain['p99']:.2f}; Rerun queue drops "
                f"{r['end_to_end_rerun'].get('rerun_dropped', 0)} |"
            )
    return lines


def _capacity_and_accuracy_rows(r: dict[str, Any]) -> list[str]:
    c = r["capacity"]
    steps = ", ".join(f"{s['tracker_hz']:.0f} Hz: {s['received']}/{s['sent']}" for s in c["steps"])
    a = r["accuracy"]
    return [
        f"| capacity: highest tracker rate with no drops | "
        f"{c['highest_rate_without_drops_hz']:.0f} Hz ({steps}) |",
        f"| accuracy ({a['scenario']}), RMS position error after 5 s | keo interpolate "
        f"L={a['configured_gain']:g}: {a['interpolate_pos_mm']:.4f} mm; reference latest: "
        f"{a['latest_pos_mm']:.4f} mm; keo at best gain L={a['best_gain']:g}: "
        f"{a['best_gain_interpolate_pos_mm']:.4f} mm; reference / keo-best = "
        f"{a['reference_over_keo']:.1f} |",
    ]


def bench_table(r: dict[str, Any]) -> str:
    """The README's table of one `keo bench` run (its JSON)."""
    m = r["machine"]
    lines = [
        f"machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}"
        + (
            f"; keo's modules from compiled bytecode: {'yes' if m['keo_bytecode_cached'] else 'no'}"
            if "keo_bytecode_cached" in m
            else ""
        )
        + (" (quick run)" if r["quick"] else ""),
        "",
        "| measure | value |",
        "|---|---|",
        *_hot_path_rows(r),
    ]
    if "recording" in r:
        lines += _recording_rows(r["recording"])
    lines += _end_to_end_rows(r)
    lines += _capacity_and_accuracy_rows(r)
    return "\n".join(lines) + "\n"


def dumps(r: dict[str, Any]) -> str:
    return msgspec.json.encode(r).decode()
