"""``clblur psf SHARP BLURRED OUT [--size N] [--response SPEC]``: measure a pair's kernel."""

from __future__ import annotations

import argparse

__all__ = ["register", "run"]

SUFFIXES = (".npy", ".png", ".tif", ".tiff")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "psf", help="measure the blur kernel of a sharp / blurred pair",
        description="Estimate the blur kernel that takes SHARP to BLURRED (registered, same "
                    "size) in linear light: non-negative least squares on the images' "
                    "gradients (clblur.psf_estimation). The kernel is written centred, in "
                    "the orientation `clblur blur --psf` takes.")
    p.add_argument("sharp", help="the sharp image")
    p.add_argument("blurred", help="the blurred image, registered to the sharp one")
    p.add_argument("out", help="output kernel: .npy (float64, unit sum) or .png / .tif "
                               "(16-bit, largest weight at full scale)")
    p.add_argument("--size", type=int, default=None, metavar="N",
                   help="odd side of the window searched, px (default: grown from 15 while "
                        "the kernel reaches its edge, up to a quarter of the shorter side)")
    p.add_argument("--response", default=None, metavar="SPEC",
                   help="nominal response that linearises both images: linear, exp, exp:K, "
                        "gamma:G, srgb or a response JSON (default: linear and srgb are "
                        "tried, and the kernel that predicts the pair better is kept)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from clblur.cli.options import check_response
    from clblur.io import atomic_write, check_output, read_image, write_image
    from clblur.psf_estimation import fit_psf

    out = check_output(args.out, args.sharp, args.blurred, suffixes=SUFFIXES)
    if args.response is not None:
        check_response(args.response)
    fit = fit_psf(read_image(args.sharp), read_image(args.blurred), args.size,
                  response=args.response)
    kernel = fit.kernel
    if out.suffix.lower() == ".npy":
        atomic_write(out, lambda tmp: np.save(tmp, kernel))
    else:
        write_image(out, np.rint(kernel / kernel.max() * 65535).astype(np.uint16))
    rows, cols = np.nonzero(kernel)
    c = np.array(kernel.shape) // 2
    print(f"kernel {kernel.shape[0]} x {kernel.shape[1]} px, {rows.size} nonzero weights, "
          f"reaching {int(np.abs(rows - c[0]).max())} px vertically and "
          f"{int(np.abs(cols - c[1]).max())} px horizontally from the centre; measured in "
          f"{fit.response} light, with the blurred image's exposure {fit.gain:.3f} x the "
          f"sharp one's, it predicts the blurred image to {fit.rmse:.2f} codes RMSE -> {out}")
    return 0
