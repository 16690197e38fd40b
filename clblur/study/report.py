"""The study report: JSON document (keys fixed by issue 4), markdown summary, figures."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from clblur.study.domain import describe as describe_domain
from clblur.study.effects import EFFECT_NAMES, black_levels, channel_exponents, format_value
from clblur.study.leftover import MIN_COUNT, describe
from clblur.study.model import Group, inverse_table, null_params, shape
from clblur.study.select import Selection

__all__ = ["BASELINE_MODEL", "build_report", "figures", "grid_image", "markdown"]

BASELINE_MODEL = ("paper: Eq. 3 response v = 1 - exp(-k x) (k cancels), Eq. 9 linear-domain "
                  "average, clipped pixels at the least clipping exposure; quantisation only")


def build_report(kind: str, sel: Selection) -> dict:
    """The report document (``gain`` = held-out RMSE reduction in code values)."""
    findings = [_finding(f) for f in sel.findings]
    for e in EFFECT_NAMES:
        if e in sel.not_testable:
            findings.append({"effect": e, "significant": False, "statistic": None,
                             "p_value": None, "estimate": None, "interval": None,
                             "explanation": f"{e}: not testable on this data: "
                                            f"{sel.not_testable[e]}."})
    model = " + ".join(["paper"] + sel.effects)
    return {
        "kind": kind,
        "baseline": {"model": BASELINE_MODEL, "heldout_rmse": sel.baseline_rmse,
                     "heldout_nll": sel.baseline_nll},
        "findings": findings,
        "extended": {"model": model, "effects": list(sel.effects),
                     "params": {k: float(v) for k, v in sel.params.items()},
                     "heldout_rmse": sel.extended_rmse, "heldout_nll": sel.extended_nll},
        "gain": sel.baseline_rmse - sel.extended_rmse,
        **({} if sel.leftover is None else {"leftover": _plain(sel.leftover)}),
        **({} if sel.domain is None else {"domain": _plain(sel.domain)}),
    }


def _finding(f) -> dict:
    return {"effect": f.effect, "significant": bool(f.significant),
            "statistic": float(f.statistic), "p_value": float(f.p_value),
            "estimate": _plain(f.estimate), "interval": _plain(f.interval),
            "explanation": f.explanation}


def _plain(v):
    """``v`` for JSON: numbers as plain ints and floats (numpy's too), containers walked;
    None, flags and names as they are."""
    if v is None or isinstance(v, (bool, str)):
        return v
    if isinstance(v, int):
        return v
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return float(v)


def _sentence(text: str) -> str:
    return text[:1].upper() + text[1:] + "."


def markdown(report: dict, title: str = "Study", figures: list[str] | None = None) -> str:
    """A short markdown summary of a report (tables of findings and the gain)."""
    b, x = report["baseline"], report["extended"]
    lines = [f"# {title}", "", f"Data kind: `{report['kind']}`."
             + (f" Codes: {report['codes']}." if "codes" in report else "")
             + (" " + _sentence(report["registration"]["summary"]) if "registration" in report
                else "")
             + "".join(" " + _sentence(report[k])
                       for k in ("clipping", "padding", "moving", "psf_estimated")
                       if k in report), "",
             "| model | held-out RMSE (codes) | held-out NLL (nats/value) |", "|---|---|---|",
             f"| paper (baseline) | {b['heldout_rmse']:.3f} | {b['heldout_nll']:.3f} |",
             f"| {x['model']} | {x['heldout_rmse']:.3f} | {x['heldout_nll']:.3f} |", "",
             f"Gain: {report['gain']:.3f} code values of held-out RMSE.", "",
             "| effect | significant | t | p | estimate | 95 % interval |",
             "|---|---|---|---|---|---|"]
    for f in report["findings"]:
        t = "-" if f["statistic"] is None else f"{f['statistic']:.2f}"
        p = "-" if f["p_value"] is None else f"{f['p_value']:.2g}"
        est = "-" if f["estimate"] is None else ", ".join(
            f"{k}={format_value(v)}" for k, v in f["estimate"].items())
        ci = "-" if not f.get("interval") else ", ".join(
            f"{k} {_range(v)}" for k, v in f["interval"].items())
        lines.append(f"| {f['effect']} | {'yes' if f['significant'] else 'no'} | {t} | {p} "
                     f"| {est} | {ci} |")
    lines += ["", "Findings:", ""] + [f"- {f['explanation']}" for f in report["findings"]]
    if "leftover" in report:
        lines += ["", describe(report["leftover"])]
    if "domain" in report:
        lines += ["", describe_domain(report["domain"], report["kind"] == "exposure-series")]
    if "splits" in report:
        sp = report["splits"]
        lines += ["", f"Repeated over {sp['count']} splits of the blocks into two folds "
                  "(the first split's findings are above): selected on", "",
                  "| effect | splits | share |", "|---|---|---|"]
        lines += [f"| {e} | {round(v * sp['count'])} of {sp['count']} | {v:.2f} |"
                  for e, v in sp["selected"].items()]
        lines += ["", "Stable (selected on more than half of the splits): "
                  + (", ".join(sp["stable"]) or "none") + "."]
    if figures:
        lines += [""] + [f"![{Path(f).stem}]({f})" for f in figures]
    return "\n".join(lines) + "\n"


def _range(v: list | dict) -> str:
    """An interval ``[a, b]``, or a list of them (one per channel) or a dict (one per
    image), for the table."""
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_range(x)}" for k, x in v.items()) + "}"
    if v and isinstance(v[0], list):
        return "[" + ", ".join(_range(x) for x in v) + "]"
    return f"[{v[0]:.3g}, {v[1]:.3g}]"


def grid_image(g: Group, values: np.ndarray) -> np.ndarray:
    """Scatter per-pixel values (n,) back onto the sampling grid (NaN where not sampled)."""
    ur, uc = np.unique(g.rows), np.unique(g.cols)
    img = np.full((ur.size, uc.size), np.nan)
    img[np.searchsorted(ur, g.rows), np.searchsorted(uc, g.cols)] = values
    return img


def figures(sel: Selection, groups: list[Group], out: Path, max_groups: int = 2) -> list[str]:
    """Residual maps, a profile and the response curve as PNG files in ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from clblur.io import atomic_write

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []

    def save(fig, name):
        path = out / name
        atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=90))
        plt.close(fig)
        written.append(name)

    for gi, g in enumerate(groups[:max_groups]):
        rb = np.where(g.valid, g.target - sel.baseline_pred[gi], np.nan)
        rx = np.where(g.valid, g.target - sel.extended_pred[gi], np.nan)
        lim = float(np.nanpercentile(np.abs(rb), 99)) or 1.0
        fig, ax = plt.subplots(1, 2, figsize=(9, 3.6))
        for a, r, t in ((ax[0], rb, "paper (baseline)"), (ax[1], rx, "extended")):
            with np.errstate(invalid="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # all channels censored
                mean = np.nanmean(r, axis=1)
            im = a.imshow(grid_image(g, mean), cmap="RdBu_r", vmin=-lim, vmax=lim)
            a.set_title(f"{t}: residual (codes)")
            a.axis("off")
        fig.colorbar(im, ax=ax, shrink=0.8)
        fig.suptitle(f"{g.name}: observed - predicted, held-out")
        save(fig, f"residuals_{gi}.png")
        worst = int(np.argmax(np.where(g.valid, np.abs(g.target - sel.baseline_pred[gi]),
                                       -1.0).max(axis=1)))
        on_row = np.flatnonzero(g.rows == g.rows[worst])
        on_row = on_row[np.argsort(g.cols[on_row])]
        fig, ax = plt.subplots(figsize=(8, 3.4))
        ax.plot(g.cols[on_row], g.target[on_row].mean(axis=1), "k.", ms=3, label="observed")
        ax.plot(g.cols[on_row], sel.baseline_pred[gi][on_row].mean(axis=1), "r-", lw=1,
                label="paper")
        ax.plot(g.cols[on_row], sel.extended_pred[gi][on_row].mean(axis=1), "b-", lw=1,
                label="extended")
        ax.set_xlabel(f"column (row {g.rows[worst]}, through the largest baseline residual)")
        ax.set_ylabel("code value (channel mean)")
        ax.legend()
        save(fig, f"profile_{gi}.png")
    fig, ax = plt.subplots(figsize=(5, 4))
    codes = np.arange(256)
    t = inverse_table(null_params())
    ax.plot(t[:-1] / t[-2], codes[:-1], "k-", label="paper Eq. 3 (Imax at full scale)")
    # the extended curve once, or once per channel where their black levels or exponents
    # differ
    ext = {**null_params(), **sel.params}
    channels = groups[0].channels if groups else 1
    levels = black_levels(ext, channels)
    factors = channel_exponents(ext, channels)
    colours = ("r", "g", "b") if channels == 3 else ("b",) * channels
    names = ("R", "G", "B") if channels == 3 else tuple(str(c) for c in range(channels))
    distinct = len(set(zip(levels, factors, strict=True))) > 1
    for c in range(channels if distinct else 1):
        t = inverse_table(ext, shape(ext, factors[c]), beta=levels[c])
        label = f"extended, {names[c]}" if distinct else "extended"
        ax.plot(t[:-1] / t[-2], codes[:-1], f"{colours[c]}--", label=label)
    ax.set_xlabel("relative exposure (code 254 = 1)")
    ax.set_ylabel("code value")
    ax.set_xlim(0, 1)
    ax.legend()
    ax.set_title("response")
    save(fig, "response.png")
    if sel.leftover is not None:
        save(_leftover_figure(plt, sel.leftover, names, colours), "leftover.png")
    return written


def _leftover_figure(plt, left: dict, names: tuple, colours: tuple):
    """What the extended model leaves, per code (``study.leftover``'s pooled offsets): the
    mean residual of each bin and channel that holds enough values in both folds to have an
    offset of its own."""
    prof = left["by_code"]
    off = np.asarray(prof["offsets"], float)
    cnt = np.asarray(prof["counts"], float)
    width = prof["bin_codes"]
    mid = (np.arange(off.shape[1]) + 0.5) * width
    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.axhline(0.0, color="k", lw=0.8)
    for c in range(off.shape[0]):
        held = cnt[c] >= 2 * MIN_COUNT  # fewer in a fold: no offset of its own (leftover)
        ax.plot(mid[held], off[c, held], "o-", color=colours[c], ms=3, lw=1,
                label=names[c] if off.shape[0] > 1 else None)
    ax.set_xlabel("code (the model's estimate of the noise-free value)")
    ax.set_ylabel("observed - model (codes)")
    verdict = "structure left" if left["structure"] else "no structure left"
    ax.set_title(f"what the model leaves: {verdict} (t = {prof['statistic']:.1f} pooled)")
    if off.shape[0] > 1:
        ax.legend()
    fig.tight_layout()
    return fig

