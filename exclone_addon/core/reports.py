"""The one-line reports a user reads after cloning (operator reports, command-line output)."""


def listed(names, most=4):
    """The first `most` names for a message, "..." if there are more."""
    names = [str(name) for name in names]
    return ", ".join(names[:most]) + (", ..." if len(names) > most else "")


def fit_error(quality, sized=False):
    """"fit error 0.2%" from a clone's quality dict ("... of the target's size" if sized); for a
    target made from the source's base mesh (cloning.fit_faces with shared_vertices), that it
    is; "" if neither."""
    shared = quality.get("shared_vertices")
    if shared is not None:
        return f"the source's own base mesh ({shared:,} vertices matched, no registration)"
    fit = quality.get("registration_mean_distance_rel")
    if fit is None:
        return ""
    return f"fit error {100 * fit:.2g}%" + (" of the target's size" if sized else "")


def summary(added, replaced, skipped, seconds, quality):
    """One-line report, e.g. "52 shape keys added in 1.8 s, fit error 0.2%"."""
    parts = [f"{len(added)} shape keys added"]
    if replaced:
        parts.append(f"{len(replaced)} replaced")
    if skipped:
        parts.append(f"{len(skipped)} skipped (already exist: {listed(skipped, most=3)})")
    text = ", ".join(parts) + f" in {seconds:.1f} s"
    fit = fit_error(quality)
    return f"{text}, {fit}" if fit else text


def measures_clause(summary):
    """The expression measures in one short clause, e.g. "blink gap L 5% R 8%, stretch 2.1x the
    source's, 11 flipped, 0 beyond the source's" from expression_measures.summary ("" if nothing
    was measured). The stretch is the excess over the source's own where the source was measured
    beside the clone (a jawOpen stretches the source's lips too), else the raw edge stretch."""
    parts = []
    gaps = [(side, summary.get(f"eyeBlink_{side}_gap")) for side in ("L", "R")]
    gaps = [f"{side} {100 * gap:.0f}%" for side, gap in gaps if gap is not None]
    if gaps:
        parts.append("blink gap " + " ".join(gaps))
    if summary.get("worst_edge_stretch") is not None:
        parts.append(stretch_phrase(summary))
        parts.append(flips_phrase(summary))
    return ", ".join(parts)


def flips_phrase(summary):
    """"3 flipped, 0 beyond the source's" (the worst counts of expression_measures.summary; the
    second where the source was measured beside the clone), else "3 flipped"."""
    phrase = f"{summary['worst_flipped_triangles']} flipped"
    excess = summary.get("worst_excess_flips")
    return phrase if excess is None else f"{phrase}, {excess} beyond the source's"


def stretch_phrase(summary):
    """"stretch 2.1x the source's" (the worst excess stretch) where expression_measures.summary
    has it, else "stretch 3.4x" (the worst raw edge stretch)."""
    excess = summary.get("worst_excess_stretch")
    if excess is not None:
        return f"stretch {excess:.1f}x the source's"
    return f"stretch {summary['worst_edge_stretch']:.1f}x"
