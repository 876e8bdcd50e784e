"""The report of ``aisdf bench change`` (:mod:`aisdf.bench.change`): every figure with its
target and whether it is met, as rows and as a markdown table."""

from __future__ import annotations



def _yes(ok: bool | None) -> str:
    return "-" if ok is None else ("yes" if ok else "no")


def rows(res: dict) -> list[tuple[str, str, str, str]]:
    """(criterion, figure, target, met) of every part that ran."""
    out = []
    c = res.get("cart")
    if c:
        s = c["standing"]["occupied"]
        late = "" if c["standing"].get("before_removal", True) else " (measured after the removal!)"
        out.append((f"cart: its volume answered occupied while it stands{late}", f"{100 * s:.1f} %", ">= 80 %",
                    _yes(s >= 0.8)))
        out.append(("(beside it: a box of the office that never moved, answered occupied)",
                    f"{100 * c['standing']['still_occupied']:.1f} %", "", ""))
        if "occupied_unknown" in c["standing"]:
            su = c["standing"]["occupied_unknown"]
            out.append(("cart: the same for a planner treating unknown space as occupied (min(sdf, unknown), 1.6)",
                        f"{100 * su:.1f} % (the still box {100 * c['standing']['still_occupied_unknown']:.1f} %)",
                        ">= 80 %", _yes(su >= 0.8)))
        if "occupied_unknown" in c.get("after", {}):
            out.append(("cart: at the end, for a planner treating unknown space as occupied",
                        f"{100 * c['after']['occupied_unknown']:.1f} %", "<= 5 %",
                        _yes(c["after"]["occupied_unknown"] <= 0.05)))
        w = c["watch"]
        at10 = next((x["occupied"] for x in w if x["after_s"] == 10), w[-1]["occupied"])
        out.append((f"cart: still occupied 0 / {min(10, w[-1]['after_s'])} / {w[-1]['after_s']} s after the last "
                    "keyframe that saw it gone", f"{100 * w[0]['occupied']:.1f} / {100 * at10:.1f} / "
                    f"{100 * w[-1]['occupied']:.1f} %", "", ""))
        t = c["cleared_after_s"]
        out.append(("cart: time until <= 5 % occupied", f"{t} s" if t is not None else
                    f"not within {w[-1]['after_s']} s", "<= 10 s", _yes(t is not None and t <= 10)))
        if c.get("first_empty_frame") is not None:
            t1 = c.get("cleared_since_first_s")
            gap = c["seen_empty_t_s"] - c["first_empty_t_s"]
            out.append((f"(the same, from the first keyframe that saw it gone, {gap:.0f} s before the last)",
                        f"{t1} s" if t1 is not None else "not within the watch", "", ""))
        out.append(("cart: rest of the room's mean error, standing -> after",
                    f"{c['standing']['room_error_cm']:.2f} -> {c['after']['room_error_cm']:.2f} cm "
                    f"(x{c['room_ratio']:.2f})", "<= x1.10", _yes(c["room_ratio"] <= 1.10)))
    p = res.get("person")
    if p:
        out.append((f"person: most negative served - truth over its swept volume, {p['after_s']:g} s after",
                    f"{100 * p['worst_below_m']:+.1f} cm", ">= -20 cm", _yes(p["worst_below_m"] >= -0.20)))
        out.append(("person: swept volume answered occupied", f"{100 * p['occupied']:.1f} %", "", ""))
    d = res.get("drift")
    if d:
        fixed = "corrected" if d["corrections_available"] else \
            f"NOT corrected ({(d.get('corrections_error') or 'no aisdf.poses').split(':')[0]})"
        out.append((f"drift: mean error +{res['args']['after_s']:g} s, {fixed} vs true poses",
                    f"{d['drift_after']['error_cm']:.2f} vs {d['true_after']['error_cm']:.2f} cm (x{d['ratio']:.2f})",
                    "<= x1.2", _yes(d["ratio"] <= 1.2) if d["corrections_available"] else "-"))
        out.append(("drift: surfaces met along lines crossing walls, drifting at the end / after / true poses",
                    f"{d['drift_end']['surfaces']} / {d['drift_after']['surfaces']} / "
                    f"{d['true_after']['surfaces']}", "1 each (after)",
                    _yes(all(x == 1 for x in d["drift_after"]["surfaces"])) if d["corrections_available"] else "-"))
        out.append(("drift: served sdf at the walls (cm), drifting at the end / after / true poses",
                    f"{d['drift_end'].get('at_wall_cm')} / {d['drift_after'].get('at_wall_cm')} / "
                    f"{d['true_after'].get('at_wall_cm')}", "", ""))
        out.append(("drift: their zero crossings, drifting at the end / after / true poses",
                    f"{d['drift_end']['crossings']} / {d['drift_after']['crossings']} / "
                    f"{d['true_after']['crossings']}", "", ""))
    k = res.get("parked")
    if k:
        out.append((f"parked: keyframes kept of {k['frames']:,} frames at one pose",
                    f"{k['end']['keyframes']} ({k['redundant']:,} redundant)", "", ""))
        out.append(("parked: process memory start -> end",
                    f"{k['start']['rss_mb']} -> {k['end']['rss_mb']} MB "
                    f"({k['end']['rss_mb'] - k['start']['rss_mb']:+.1f})", "", ""))
    return out


def report(res: dict) -> str:
    a = res["args"]
    lines = [f"Changing scenes: {a['building']} (seed {a['seed']}), {a['frames']}-frame passes, mapper preset "
             f"{a['preset']}; frontend, mapper and query as processes over Zenoh on loopback; {res['date']}, "
             f"commit {res['commit']}; {res['wall_s']:.0f} s.", "",
             "| criterion | figure | target | met |", "|---|---|---|---|"]
    lines += [f"| {r[0]} | {r[1]} | {r[2]} | {r[3]} |" for r in rows(res)]
    return "\n".join(lines)
