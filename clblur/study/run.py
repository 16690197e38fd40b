"""Run a study: manifest or arrays -> groups -> diagnosis -> report (and figures)."""

from __future__ import annotations

import json
import os
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clblur.calibration.series import photometric_exposure
from clblur.errors import InputError
from clblur.io import (
    atomic_write_text,
    codec_block,
    light_channels,
    read_flow,
    read_image,
    read_psf,
    refuse_overwrite,
)
from clblur.io.paths import refuse_folder_of_inputs
from clblur.manifest import Manifest, load_manifest, manifest_inputs
from clblur.psf_estimation import fit_psf
from clblur.registration import align_series, describe
from clblur.study.model import Group
from clblur.study.pairs import pair_group
from clblur.study.report import build_report, figures, markdown
from clblur.study.select import Selection, select
from clblur.study.series import series_groups
from clblur.study.stacks import stack_group

__all__ = ["DEFAULT_PIXELS", "StudyResult", "check_report_name", "groups_from_manifest",
           "split_summary", "study", "study_groups"]

DEFAULT_PIXELS = 60000  # target pixels used in all (split evenly over pairs/stacks/steps)


@dataclass
class StudyResult:
    report: dict
    selection: Selection
    groups: list[Group]


# fewest unclipped target values a study runs on (a few hundred pixels of one image)
MIN_USABLE = 100


def _read_light(path: str | os.PathLike, dtypes: set[str] | None = None) -> np.ndarray:
    """An image file's light channels (alpha is no light: RGBA, and grey + alpha); its dtype
    is added to ``dtypes`` when given."""
    image = light_channels(read_image(path))
    if dtypes is not None:
        dtypes.add(image.dtype.name)
    return image


def groups_from_manifest(manifest: Manifest, max_pixels: int = DEFAULT_PIXELS,
                         progress: bool = False, dtypes: set[str] | None = None,
                         align: bool = True, notes: dict | None = None) -> list[Group]:
    """Read the manifest's images and build the study groups of its kind; ``dtypes``, when
    given, collects the images' stored dtypes (the report says when 16-bit was rounded).
    ``align``: register an exposure series' images and crop them to their common window
    (``clblur.registration``, as ``clblur calibrate`` does); ``notes``, when
    given, receives the registration (``notes["registration"]``,
    ``clblur.registration.describe``) and lines on what was left out as no light:
    ``notes["clipping"]`` (a camera that clips below full scale), ``notes["padding"]``
    (constant borders, ``clblur.study.series.series_groups``), ``notes["moving"]`` (what
    does not show one static scene) and ``notes["psf_estimated"]``
    (blur pairs whose kernel was measured from the pair, ``"psf": "estimate"``)."""
    from tqdm import tqdm

    def read(path: str | os.PathLike) -> np.ndarray:
        return _read_light(path, dtypes)

    if manifest.kind == "exposure-series":
        imgs = [read(e.path) for e in manifest.images]
        if align:
            reg = align_series(imgs, photometric_exposure(
                [e.exposure for e in manifest.images], [e.f_number for e in manifest.images]))
            # Every whole-pixel move is cut away, one of a pixel too: the misregistration
            # effect is one shift shared by every step, and a frame that moved shifts its
            # two neighbouring steps in opposite directions (and the steps two stops apart
            # by other amounts), so no shared shift fits it.  What the effect can test is
            # the sub-pixel rest.  (Leaving Canon's one-row move of 0.5.JPG to the effect
            # raised the extended model's held-out RMSE from 2.53 to 2.69 codes,
            # docs/studies/validation.md.)
            imgs = [reg.crop(im, i) for i, im in enumerate(imgs)]
            if notes is not None:
                notes["registration"] = describe(reg, [e.path.name for e in manifest.images])
        left_out: dict = {}
        # a JPEG's clipped highlight biases the blocks around it (``series._clipped_near``)
        block = max(codec_block(e.path) for e in manifest.images)
        groups = series_groups(imgs, [e.exposure for e in manifest.images],
                               [e.f_number for e in manifest.images], max_pixels=max_pixels,
                               notes=left_out, names=[e.path.name for e in manifest.images],
                               block=block)
        if notes is not None and (left_out["clip_code"] < 255 or left_out["clipped_sources"]):
            top = left_out["clip_code"]
            near = (f", which bounds its light from below only, or within {block} pixels of "
                    f"a clipped region (the images are coded in {block}-pixel blocks: the "
                    "codec's ringing pulls a clipped plateau's pixels below the clip and "
                    "shifts its blocks' other values)" if block > 1 else
                    " or beside one, which bounds its light from below only")
            notes["clipping"] = (
                (f"the series clips at code {top} of 255 (a pile below full scale, or "
                 "clipped pixels that read below it: noise added after the clip): targets "
                 "at or above it are censored; " if top < 255 else "")
                + f"{100 * left_out['clipped_sources']:.1f} % of the sampled values have a "
                  f"source at code {top}{near}, and are left out")
        if notes is not None and left_out["padding"]:
            frames = ", ".join(f"{manifest.images[i].path.name} {100 * f:.1f} %"
                               for i, f in sorted(left_out["padding"].items()))
            notes["padding"] = (f"constant borders padded into the frames hold no light and "
                                f"are left out: {frames}")
        if notes is not None and left_out["moving"]:
            notes["moving"] = (f"{100 * left_out['moving']:.1f} % of the pixels do not show one "
                               "static scene (something moved between exposures, or a border "
                               "differs; clblur.calibration.ghosts) and are left out")
        return groups
    if manifest.kind == "blur-pair":
        per = max(1000, max_pixels // len(manifest.pairs))
        out = []
        measured = []
        for i, p in enumerate(tqdm(manifest.pairs, desc="pairs", disable=not progress)):
            static, blurred = read(p.static), read(p.blurred)
            if p.motion is not None:
                motion = p.motion
            elif p.flow is not None:
                motion = read_flow(p.flow)
            elif p.estimate_psf:
                fit = fit_psf(static, blurred, p.psf_size)
                motion = fit.kernel
                measured.append(f"{Path(p.blurred).name} {motion.shape[0]} x "
                                f"{motion.shape[1]} px ({fit.response} light, exposure "
                                f"gain {fit.gain:.3f})")
            else:
                motion = read_psf(p.psf)
            out.append(pair_group(static, blurred, motion,
                                  anchor=p.anchor, exposure_ratio=p.exposure_ratio,
                                  max_pixels=per, name=f"pair{i}:{Path(p.blurred).name}"))
        if notes is not None and measured:
            notes["psf_estimated"] = ("the blur kernels were measured from the pairs "
                                      "(clblur.psf_estimation, in the nominal light named): "
                                      + ", ".join(measured))
        return out
    per = max(1000, max_pixels // len(manifest.stacks))
    return [stack_group([read(f) for f in s.frames], read(s.long), max_pixels=per,
                        name=f"stack{i}:{Path(s.long).name}")
            for i, s in enumerate(tqdm(manifest.stacks, desc="stacks", disable=not progress))]


def study_groups(kind: str, groups: list[Group], *, alpha: float = 0.05,
                 progress: bool = False, splits: int = 1) -> StudyResult:
    """Diagnose prepared groups (see ``clblur.study.select``) and build the report.

    ``splits`` > 1 repeats the whole diagnosis on that many splits of the blocks into two
    folds (the checkerboard first, then random halves, ``assign_blocks``) and adds to the
    report how often each effect was selected (``report["splits"]``).  One split's verdict
    can turn on which half fitted which model: the likelihood of a free response shape and
    the noise has several optima, and an effect whose held-out gain is near the threshold
    joins on some splits and not others (repeated sample splitting, Chernozhukov et al. 2018,
    Sec. 3.4; stability selection, Meinshausen & Buehlmann 2010).  The findings, estimates
    and predictions are the first split's; ``stable`` lists the effects selected on more
    than half of the splits.
    """
    from tqdm import tqdm

    if not groups:
        raise InputError("nothing to study: no pairs, stacks or exposure steps")
    if not 0 < alpha < 1:
        raise InputError(f"alpha must be in (0, 1), got {alpha}")
    _check_splits(splits)
    chosen = []
    for s in reversed(range(splits)):  # the first split last: its folds stay assigned
        with tqdm(desc=f"effect tests, split {s + 1}/{splits}" if splits > 1
                  else "effect tests", unit="test", disable=not progress) as bar:
            sel = select(groups, alpha=alpha, progress=bar, split=s)
        chosen.append(list(sel.effects))
    report = build_report(kind, sel)
    if splits > 1:
        report["splits"] = split_summary(chosen[::-1])
    return StudyResult(report, sel, groups)


def _check_splits(splits: int) -> None:
    if not isinstance(splits, int) or isinstance(splits, bool) or splits < 1:
        raise InputError(f"splits must be an integer >= 1, got {splits!r}")


def split_summary(chosen: list[list[str]]) -> dict:
    """How often each effect was selected over repeated splits (``chosen``: the selected
    effects of each split, the first split first)."""
    n = len(chosen)
    times = Counter(e for c in chosen for e in set(c))
    selected = {e: times[e] / n for e in sorted(times, key=lambda e: (-times[e], e))}
    return {"count": n, "selected": selected,
            "stable": [e for e, v in selected.items() if v > 0.5],
            "per_split": chosen}


def check_report_name(report: str | os.PathLike, option: str = "report") -> None:
    """Refuse a report named ``.md``: its summary, written beside it, would replace it."""
    if Path(report).suffix.lower() == ".md":
        raise InputError(f"{option} {report}: name the JSON report (.json); its .md summary "
                         "is written beside it")


def study(manifest: str | os.PathLike | Manifest, *, report: str | os.PathLike | None = None,
          figures_dir: str | os.PathLike | None = None, max_pixels: int = DEFAULT_PIXELS,
          alpha: float = 0.05, progress: bool = False, splits: int = 1,
          align: bool = True) -> StudyResult:
    """The API equivalent of ``clblur study``: run, and write the report (JSON, plus a
    ``.md`` summary beside it) and figures when asked.  ``splits``: see ``study_groups``;
    ``align``: see ``groups_from_manifest`` (the report's ``registration``)."""
    m = manifest if isinstance(manifest, Manifest) else load_manifest(manifest)
    if not isinstance(max_pixels, int) or max_pixels < 1000:
        raise InputError(f"max_pixels must be an integer >= 1000, got {max_pixels!r}")
    _check_splits(splits)
    inputs = manifest_inputs(m)
    if report is not None:  # refuse before the work, not after
        if not Path(report).parent.is_dir():
            raise InputError(f"output folder does not exist: {Path(report).parent}")
        check_report_name(report)
        refuse_overwrite(report, *inputs)
        refuse_overwrite(Path(report).with_suffix(".md"), *inputs)
    if figures_dir is not None:  # its figures have fixed names
        refuse_folder_of_inputs(figures_dir, inputs, "figures folder")
    dtypes: set[str] = set()
    notes: dict = {}
    groups = groups_from_manifest(m, max_pixels, progress, dtypes, align, notes)
    usable = sum(int(g.valid.sum()) for g in groups)
    sampled = sum(int(g.valid.shape[0]) for g in groups)
    if sampled < MIN_USABLE:  # too few target pixels whose whole path lies in the image
        raise InputError(f"manifest {m.path}: only {sampled} target pixels can be sampled "
                         "(a pixel's whole blur path or kernel must lie inside the image): "
                         "the images are too small for their motion or kernel")
    if usable < MIN_USABLE:  # nothing between black and white: nothing to fit or score
        raise InputError(f"manifest {m.path}: only {usable} sampled pixel values lie between "
                         "the black and white clipping codes; the images are saturated or "
                         "black")
    result = study_groups(m.kind, groups, alpha=alpha, progress=progress, splits=splits)
    result.report.update(notes)
    if "uint16" in dtypes:
        result.report["codes"] = ("16-bit images rounded to 8-bit codes (x / 257) at entry; "
                                  "the study's likelihood is written in 8-bit codes")
    names = []
    if figures_dir is not None:
        names = [str(Path(figures_dir) / n) for n in
                 figures(result.selection, groups, Path(figures_dir))]
    if report is not None:
        report = Path(report)
        atomic_write_text(report, json.dumps(result.report, indent=1) + "\n")
        links = [os.path.relpath(n, report.parent) for n in names]  # relative to the .md
        atomic_write_text(report.with_suffix(".md"),
                          markdown(result.report, f"Study of {m.path.name}", links))
    return result
