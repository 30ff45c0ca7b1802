"""Plot the LNT / LNT-sparse Q-ensembles over training, from the rows `lnt_critics.py --csv` wrote.

    python results/100000/probes/plot_series.py results/100000/probes/series_lnt_seed2.csv [...]

One figure per series file, written beside it as a PNG: the members' means on the reset replay at
the reset policy's actions (the band from the lowest to the highest member, the ensemble mean, the
minimum over members that the trigger compares with Q_thresh) against [0, 100], where every true
value lies (rewards in [0, 1], gamma = 0.99), and the share of replay rows the trigger would cut
(minimum over members below Q_thresh).
"""
import argparse
import csv
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def plot(path: Path, upper: float = 100.0) -> Path:
    with path.open() as f:
        rows = sorted((dict((k, float(v)) for k, v in r.items()) for r in csv.DictReader(f)),
                      key=lambda r: r["step"])
    if not rows:
        raise SystemExit(f"{path} has no rows")
    q_thresh = rows[0]["q_thresh"]
    step = [r["step"] / 1000 for r in rows]
    figure, (values, cut) = plt.subplots(2, 1, figsize=(7, 6), sharex=True,
                                         gridspec_kw={"height_ratios": [3, 1]})
    values.fill_between(step, [r["lowest_member"] for r in rows], [r["highest_member"] for r in rows],
                        alpha=0.25, label="members' means: lowest to highest")
    values.plot(step, [r["q_mean"] for r in rows], marker=".", label="ensemble mean over rows")
    values.plot(step, [r["q_min_over_members"] for r in rows], marker=".",
                label="minimum over members (the trigger's value), mean over rows")
    values.axhline(q_thresh, color="k", ls=":", label=f"Q_thresh = {q_thresh:g}")
    values.axhline(0, color="grey", lw=0.8)
    values.axhline(upper, color="grey", lw=0.8, ls="--", label=f"true values lie in [0, {upper:g}]")
    values.set_ylabel("Q on the reset replay, at pi_r(s)")
    values.legend(fontsize=8)
    values.set_title(path.stem.replace("series_", "").replace("_", " "))
    cut.plot(step, [100 * r["below_thresh"] for r in rows], marker=".")
    cut.set_ylabel("% rows below\nQ_thresh")
    cut.set_xlabel("steps (thousands)")
    cut.set_ylim(-5, 105)
    figure.tight_layout()
    out = path.with_suffix(".png")
    figure.savefig(out, dpi=110)
    plt.close(figure)
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("series", type=Path, nargs="+", help="CSV files written by lnt_critics.py --csv")
    args = parser.parse_args(argv)
    for path in args.series:
        print(plot(path))


if __name__ == "__main__":
    main()
