"""Every command against a corpus of hostile inputs (issue 10).

For each case: exit code 2 (or 0 where the input is legal), exactly one line on stderr that
names the problem, no traceback, nothing written outside the output, no partial output, every
input byte-identical afterwards.  The corpus is built in a temporary folder:

    root/in/        inputs (valid, truncated, zero-byte, wrong-magic files of every format...)
    root/outside/   files a traversal would reach (victim.png); nothing may change here
    root/cwd/       the working directory of every command
    root/out_<id>/  the case's output folder (OUT)

Commands run in-process through ``clblur.cli.main`` with stderr captured at the file
descriptor (so C libraries' messages count too); a few run in a subprocess.
"""

from __future__ import annotations

import hashlib
import json
import os
import struct
import subprocess
import sys
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import tifffile
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import clblur
from clblur.cli import main
from clblur.io import write_flow, write_image

try:
    import av
except ImportError:  # video extra not installed: the mp4 cases are skipped
    av = None

H, W = 12, 16


@pytest.fixture(autouse=True)
def _quiet(monkeypatch):
    monkeypatch.setenv("CLBLUR_QUIET", "1")


# --------------------------------------------------------------------------- the corpus
def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return (struct.pack(">I", len(data)) + kind + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))


def _png_claiming(w: int, h: int) -> bytes:
    """A tiny PNG whose header claims ``w`` x ``h`` RGB pixels."""
    return (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + _png_chunk(b"IDAT", zlib.compress(b"\0" * 64)) + _png_chunk(b"IEND", b""))


def _jpeg_claiming(good: bytes, w: int, h: int) -> bytes:
    """A valid JPEG with its SOF0 size fields rewritten."""
    i = good.index(b"\xff\xc0")
    return good[:i + 5] + struct.pack(">HH", h, w) + good[i + 9:]


def _write_mp4(path: Path, n: int = 4) -> None:
    rng = np.random.default_rng(1)
    c = av.open(str(path), "w")
    s = c.add_stream("mpeg4", rate=10)
    s.width, s.height, s.pix_fmt = W, H, "yuv420p"
    for _ in range(n):
        frame = av.VideoFrame.from_ndarray(rng.integers(0, 256, (H, W, 3), np.uint8),
                                           format="rgb24")
        for pkt in s.encode(frame):
            c.mux(pkt)
    for pkt in s.encode():
        c.mux(pkt)
    c.close()


def _save_raw(path: Path, array) -> None:
    np.save(path, array, allow_pickle=True)


def build_corpus(root: Path) -> None:
    rng = np.random.default_rng(10)
    d = root / "in"
    for sub in ("in", "outside", "cwd", "in/flows", "in/seq", "in/series", "in/symflows",
                "in/symseq", "in/symseries", "in/symin", "in/sub", "in/folder.png",
                "in/folder.npy"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    img = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    write_image(root / "outside" / "victim.png", img)
    np.save(root / "outside" / "victim.npy", np.zeros((H, W, 2), np.float32))
    (root / "outside" / "victim.json").write_text(json.dumps(clblur.Gamma(2.0).to_dict()))
    good = {}
    for ext in ("png", "jpg", "tif", "bmp", "webp"):
        write_image(d / f"good.{ext}", img)
        good[ext] = (d / f"good.{ext}").read_bytes()
    write_image(d / "grey16.png", rng.integers(0, 65536, (H, W), dtype=np.uint16))
    write_image(d / "rgba.png", rng.integers(0, 256, (H, W, 4), dtype=np.uint8))
    write_image(d / "float.tif", rng.random((H, W, 3)).astype(np.float32))
    write_image(d / "ünï cødé.png", img)
    write_image(d / "with space.png", img)
    write_image(d / "sub" / "nested.png", img)
    flow = rng.normal(0, 2, (H, W, 2)).astype(np.float32)
    np.save(d / "flow.npy", flow)
    write_flow(d / "flow.flo", flow)
    np.save(d / "flow ü.npy", flow)
    np.save(d / "psf.npy", np.ones((1, 5)))
    clblur.Gamma(1.8).save(d / "resp.json")

    # every accepted format: zero bytes, truncated, wrong magic
    samples = dict(good)
    samples["npy"] = (d / "flow.npy").read_bytes()
    samples["flo"] = (d / "flow.flo").read_bytes()
    samples["json"] = (d / "resp.json").read_bytes()
    samples["csv"] = b"image,dx,dy\ngood.png,1,0\n"
    if av is not None:
        _write_mp4(d / "good.mp4")
        samples["mp4"] = (d / "good.mp4").read_bytes()
    for ext, data in samples.items():
        (d / f"zero.{ext}").write_bytes(b"")
        (d / f"trunc.{ext}").write_bytes(data[:len(data) // 2])
        (d / f"magic.{ext}").write_bytes(b"GIF89a\x00\x01" + bytes(rng.integers(0, 256, 300,
                                                                           dtype=np.uint8)))
    # damage inside the pixel data, where a header check does not look
    crc = bytearray(good["png"])
    crc[crc.find(b"IDAT") + 10] ^= 0x55  # one flipped byte: the chunk fails its CRC
    (d / "crc.png").write_bytes(bytes(crc))
    texture = rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)
    write_image(d / "tex.jpg", texture)
    scan = bytearray((d / "tex.jpg").read_bytes())
    mid = scan.find(b"\xff\xda") + (len(scan) - scan.find(b"\xff\xda")) // 2
    scan[mid:mid + 24] = b"\xff" * 23 + b"\x5a"  # a stray marker inside the scan
    (d / "scan.jpg").write_bytes(bytes(scan))
    tifffile.imwrite(d / "lzw.tif", texture, photometric="rgb", tile=(16, 16),
                     compression="lzw")
    tifffile.imwrite(d / "bilevel.tif", texture[..., 0] > 128)  # 1 bit: no dtype clblur takes
    lzw = bytearray((d / "lzw.tif").read_bytes())
    with tifffile.TiffFile(d / "lzw.tif") as tif:
        at = int(tif.pages[0].dataoffsets[5])
    lzw[at:at + 32] = bytes(range(160, 192))
    (d / "lzwbad.tif").write_bytes(bytes(lzw))
    (d / "headonly.png").write_bytes(good["png"][:40])
    (d / "pngas.jpg").write_bytes(good["png"])  # mislabelled: a PNG named .jpg
    (d / "bomb.png").write_bytes(_png_claiming(100000, 100000))
    (d / "big.png").write_bytes(_png_claiming(30000, 30000))
    (d / "zerodims.png").write_bytes(_png_claiming(0, 0))
    (d / "bomb.jpg").write_bytes(_jpeg_claiming(good["jpg"], 65000, 65000))
    (d / "text.png").write_text("hello, not an image")

    # flows and PSFs: NaN, inf, huge, wrong shape, wrong dtype
    bad_flows = {
        "nan": np.where(np.arange(H * W * 2).reshape(H, W, 2) == 5, np.nan, flow),
        "inf": np.full((H, W, 2), np.inf, np.float32),
        "ninf": np.full((H, W, 2), -np.inf, np.float32),
        "huge": np.full((H, W, 2), 1e9, np.float32),
        "huge1": np.where(np.arange(H * W * 2).reshape(H, W, 2) == 7, 1e9, 0).astype(np.float32),
        "shape3": np.zeros((H, W, 3), np.float32),
        "shape2d": np.zeros((H, W), np.float32),
        "shape4d": np.zeros((1, H, W, 2), np.float32),
        "wrongsize": np.zeros((5, 5, 2), np.float32),
        "empty": np.zeros((0, 0, 2), np.float32),
        "complex": np.zeros((H, W, 2), np.complex64),
        "bool": np.zeros((H, W, 2), bool),
        "strings": np.full((H, W, 2), "a"),
        "f16": flow.astype(np.float16),
        "int": np.ones((H, W, 2), np.int16),
        "fortran": np.asfortranarray(flow),
    }
    for name, a in bad_flows.items():
        np.save(d / f"flow_{name}.npy", a)
    _save_raw(d / "flow_pickle.npy", np.array([{"a": 1}], dtype=object))
    head = np.array([202021.25], "<f4").tobytes()
    (d / "flo_huge_dims.flo").write_bytes(head + np.array([10**9, 10**9], "<i4").tobytes())
    (d / "flo_neg_dims.flo").write_bytes(head + np.array([-4, 3], "<i4").tobytes())
    write_flow(d / "flo_nan.flo", np.full((H, W, 2), np.nan, np.float32))
    psfs = {"nan": np.full((3, 3), np.nan), "neg": -np.ones((3, 3)), "zero": np.zeros((3, 3)),
            "3d": np.ones((3, 3, 3)), "1d": np.ones(5), "long": np.ones((1, 5000), np.uint8),
            "inf": np.full((2, 2), np.inf)}
    for name, a in psfs.items():
        np.save(d / f"psf_{name}.npy", a)

    # response documents
    responses = {
        "resp_notobject.json": "[1, 2, 3]",
        "resp_unknown.json": json.dumps({"format": "clblur-response", "kind": "warp"}),
        "resp_nan.json": '{"format": "clblur-response", "version": 1, "kind": "gamma", '
                         '"params": {"gamma": NaN}}',
        "resp_deep.json": "[" * 100000 + "]" * 100000,
        "resp_latin1.json": "{\"k\": \"\xe9\"}".encode("latin-1"),
        "resp_table_bad.json": json.dumps({"format": "clblur-response", "version": 1,
                                           "kind": "table", "values": [0.5, 0.2, "x"]}),
    }
    for name, text in responses.items():
        (d / name).write_bytes(text if isinstance(text, bytes) else text.encode())

    # symlinks out of their allowed folder
    (d / "symin" / "ok.png").write_bytes(good["png"])
    (d / "symin" / "escape.png").symlink_to(root / "outside" / "victim.png")
    (d / "link_out.png").symlink_to(root / "outside" / "victim.png")
    (d / "link_out.npy").symlink_to(root / "outside" / "victim.npy")
    (d / "link_out.json").symlink_to(root / "outside" / "victim.json")
    (d / "symflows" / "forward_000000.npy").symlink_to(root / "outside" / "victim.npy")
    (d / "symseq" / "f0.png").write_bytes(good["png"])
    (d / "symseq" / "f1.png").symlink_to(root / "outside" / "victim.png")
    (d / "symseries" / "a.png").write_bytes(good["png"])
    (d / "symseries" / "b.png").symlink_to(root / "outside" / "victim.png")
    (d / "symseries" / "times.txt").write_text("a.png 1/100\nb.png 1/50\n")
    for i in range(3):
        (d / "seq" / f"f{i}.png").write_bytes(good["png"])
    (d / "batchin" / "sub").mkdir(parents=True)
    for name in ("good.png", "good.jpg", "with space.png", "ünï cødé.png", "sub/nested.png"):
        (d / "batchin" / name).write_bytes((d / name).read_bytes())
    (d / "symbflows").mkdir()
    (d / "symbflows" / "good.npy").symlink_to(root / "outside" / "victim.npy")
    (d / "seq" / "f3.png").write_bytes(b"")
    (d / "flows" / "forward_000000.npy").write_bytes(b"\x93NUMPY garbage")
    (d / "series" / "a.png").write_bytes(good["png"])
    (d / "series" / "times.txt").write_text("1/100\nfast\n")

    # study / calibration manifests
    def manifest(name: str, doc) -> None:
        (d / name).write_text(doc if isinstance(doc, str) else json.dumps(doc))

    pair = {"static": "good.png", "blurred": "good.png", "motion": [2, 0]}
    manifest("m_pairs_empty.json", {"kind": "blur-pair", "pairs": []})
    manifest("m_pairs_traversal.json", {"kind": "blur-pair", "pairs": [
        {**pair, "static": "../outside/victim.png"}]})
    manifest("m_pairs_absolute.json", {"kind": "blur-pair", "pairs": [
        {**pair, "blurred": str(root / "outside" / "victim.png")}]})
    manifest("m_pairs_symlink.json", {"kind": "blur-pair", "pairs": [
        {**pair, "static": "link_out.png"}]})
    manifest("m_pairs_flow_out.json", {"kind": "blur-pair", "pairs": [
        {"static": "good.png", "blurred": "good.png", "flow": "../outside/victim.npy"}]})
    manifest("m_pairs_motion_text.json", {"kind": "blur-pair", "pairs": [
        {**pair, "motion": ["a", "b"]}]})
    manifest("m_pairs_motion_nan.json", '{"kind": "blur-pair", "pairs": [{"static": '
             '"good.png", "blurred": "good.png", "motion": [NaN, 0]}]}')
    manifest("m_pairs_two_forms.json", {"kind": "blur-pair", "pairs": [
        {**pair, "psf": "psf.npy"}]})
    manifest("m_pairs_psf_size.json", {"kind": "blur-pair", "pairs": [
        {"static": "good.png", "blurred": "good.png", "psf": "estimate", "psf_size": 4}]})
    manifest("m_pairs_estimate_shapes.json", {"kind": "blur-pair", "pairs": [
        {"static": "good.png", "blurred": "grey16.png", "psf": "estimate"}]})
    manifest("m_pairs_path_number.json", {"kind": "blur-pair", "pairs": [
        {**pair, "static": 5}]})
    manifest("m_pairs_not_list.json", {"kind": "blur-pair", "pairs": {"a": 1}})
    manifest("m_kind.json", {"kind": "holiday-photos"})
    manifest("m_stack_one.json", {"kind": "frame-stack", "stacks": [
        {"frames": ["good.png"], "long": "good.png"}]})
    manifest("m_stack_traversal.json", {"kind": "frame-stack", "stacks": [
        {"frames": ["good.png", "../../etc/passwd"], "long": "good.png"}]})
    manifest("m_series_empty.json", {"kind": "exposure-series", "images": []})
    manifest("m_series_traversal.json", {"kind": "exposure-series", "images": [
        {"path": "good.png", "exposure": 1}, {"path": "../outside/victim.png", "exposure": 2}]})
    manifest("m_series_negative.json", {"kind": "exposure-series", "images": [
        {"path": "good.png", "exposure": -1}, {"path": "good.jpg", "exposure": 2}]})
    manifest("m_series_missing.json", {"kind": "exposure-series", "images": [
        {"path": "nope.png", "exposure": 1}, {"path": "nada.png", "exposure": 2}]})
    # numbers JSON holds but a float cannot, booleans as numbers, one file listed twice
    manifest("m_series_huge.json", '{"kind": "exposure-series", "images": [{"path": '
             '"good.png", "exposure": 1' + "0" * 400 + '}, {"path": "good.jpg", '
             '"exposure": 2}]}')
    manifest("m_series_bool.json", {"kind": "exposure-series", "images": [
        {"path": "good.png", "exposure": True}, {"path": "good.jpg", "exposure": 2}]})
    manifest("m_series_twice.json", {"kind": "exposure-series", "images": [
        {"path": "good.png", "exposure": 1}, {"path": "good.png", "exposure": 2}]})
    manifest("m_series_inputs.json", {"kind": "exposure-series", "images": [
        {"path": "series/a.png", "exposure": 1}, {"path": "good.png", "exposure": 2}]})
    manifest("m_pairs_motion_huge.json", '{"kind": "blur-pair", "pairs": [{"static": '
             '"good.png", "blurred": "good.png", "motion": [1' + "0" * 400 + ', 0]}]}')
    manifest("m_pairs_motion_bool.json", {"kind": "blur-pair", "pairs": [
        {**pair, "motion": [True, False]}]})
    manifest("m_pairs_ratio_huge.json", '{"kind": "blur-pair", "pairs": [{"static": '
             '"good.png", "blurred": "good.png", "motion": [2, 0], "exposure_ratio": 1'
             + "0" * 400 + '}]}')
    manifest("m_pairs_anchor_list.json", {"kind": "blur-pair", "pairs": [
        {**pair, "anchor": ["start"]}]})
    manifest("m_pairs_motion_long.json", {"kind": "blur-pair", "pairs": [
        {**pair, "motion": [500, 0]}]})  # longer than the image: no path fits in it
    (d / "times_huge.txt").write_text("1e400\n")
    for name in ("white_a.png", "white_b.png"):  # a series with nothing below white
        write_image(d / name, np.full((48, 64, 3), 255, np.uint8))
    manifest("m_series_white.json", {"kind": "exposure-series", "images": [
        {"path": "white_a.png", "exposure": 1}, {"path": "white_b.png", "exposure": 2}]})
    manifest("m_series_same_exposure.json", {"kind": "exposure-series", "images": [
        {"path": "good.png", "exposure": 1}, {"path": "good.jpg", "exposure": 1}]})
    manifest("m_series_fnumber_some.json", {"kind": "exposure-series", "images": [
        {"path": "good.png", "exposure": 1, "f_number": 2.8},
        {"path": "good.jpg", "exposure": 2}]})
    # times that do not belong to the images: the longer exposure is the darker image
    write_image(d / "half.png", (img // 2).astype(np.uint8))
    manifest("m_series_darker.json", {"kind": "exposure-series", "images": [
        {"path": "good.png", "exposure": 1}, {"path": "half.png", "exposure": 2}]})
    (d / "times_twice.txt").write_text("a.png 1/100\na.png 1/50\n")

    # batch manifests (CSV)
    def csv(name: str, text: str | bytes) -> None:
        (d / name).write_bytes(text if isinstance(text, bytes) else text.encode())

    victim = root / "outside" / "victim.png"
    csv("b_traversal_image.csv", "image,dx,dy\n../outside/victim.png,1,0\n")
    csv("b_traversal_deep.csv", "image,dx,dy\n../../src/x.png,1,0\n")
    csv("b_absolute_image.csv", f"image,dx,dy\n{victim},1,0\n")
    csv("b_output_up.csv", "image,output\ngood.png,../victim.png\n")
    csv("b_output_dotdot.csv", "image,output\ngood.png,..\n")
    csv("b_output_absolute.csv", f"image,output\ngood.png,{victim}\n")
    csv("b_output_subdir.csv", "image,output\ngood.png,sub/x.png\n")
    csv("b_flow_out.csv", "image,flow\ngood.png,../outside/victim.npy\n")
    csv("b_flow_abs.csv", f"image,flow\ngood.png,{root / 'outside' / 'victim.npy'}\n")
    csv("b_flow_symlink.csv", "image,flow\ngood.png,link_out.npy\n")
    csv("b_psf_out.csv", "image,psf\ngood.png,../outside/victim.png\n")
    csv("b_response_out.csv", "image,dx,dy,response\ngood.png,1,0,../outside/victim.json\n")
    csv("b_symlink_image.csv", "image,dx,dy\nescape.png,1,0\n")
    csv("b_nul.csv", "image,dx,dy\ngood\x00.png,1,0\n")
    csv("b_unknown_col.csv", "image,speed\ngood.png,3\n")
    csv("b_no_image_col.csv", "name,dx\ngood.png,1\n")
    csv("b_twice.csv", "image,dx,dy\ngood.png,1,0\ngood.png,2,0\n")
    csv("b_extra_cells.csv", "image,dx,dy\ngood.png,1,0,7,8\n")
    csv("b_latin1.csv", "image,dx,dy\n\xe9t\xe9.png,1,0\n".encode("latin-1"))
    csv("b_empty_name.csv", "image,dx,dy\n,1,0\n")
    csv("b_long_name.csv", "image,dx,dy\n" + "x" * 300 + ".png,1,0\n")  # over NAME_MAX
    csv("b_unicode_ok.csv", "image,dx,dy,output\nünï cødé.png,2,0,ü out.png\n"
                            "with space.png,1,1,\n")
    csv("b_nested_ok.csv", "image,dx,dy\nsub/nested.png,2,0\n")


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    root = tmp_path_factory.mktemp("hostile")
    build_corpus(root)
    return root


# --------------------------------------------------------------------------- the cases
@dataclass(frozen=True)
class Case:
    id: str
    argv: tuple[str, ...]  # {in}, {out}, {outside}, {root} are substituted
    code: int = 2
    match: str = ""  # a word the error line must contain (lower case)
    needs_av: bool = False
    keeps_output: bool = False  # a video that ends early keeps the frames written (by design)


NUMPY = ("--backend", "numpy")


def blur(src: str, *extra: str, code: int = 2, match: str = "",
         out: str = "{out}/o.png") -> Case:
    cid = f"blur:{src}:{' '.join(extra)}" + ("" if out == "{out}/o.png" else f"->{out}")
    return Case(cid, ("blur", src, out, *extra, *NUMPY), code, match)


def image_cases() -> list[Case]:
    cases = []
    for ext in ("png", "jpg", "tif", "bmp", "webp"):
        for kind in ("zero", "trunc", "magic"):
            cases.append(blur(f"{{in}}/{kind}.{ext}", "--motion=1,0", match="image"))
        cases.append(blur(f"{{in}}/good.{ext}", "--motion=2,1", code=0))
    cases += [
        blur("{in}/headonly.png", "--motion=1,0", match="image"),
        blur("{in}/crc.png", "--motion=1,0", match="crc"),
        blur("{in}/scan.jpg", "--motion=1,0", match="jpeg"),
        blur("{in}/lzw.tif", "--motion=1,0", code=0),
        blur("{in}/lzw.tif", "--motion=1,0", code=0, out="{out}/o.tif"),
        blur("{in}/lzwbad.tif", "--motion=1,0", match="corrupt tiff segment"),
        blur("{in}/lzwbad.tif", "--motion=1,0", match="corrupt tiff segment", out="{out}/o.tif"),
        blur("{in}/bomb.png", "--motion=1,0", match="decompression bomb"),
        blur("{in}/bomb.jpg", "--motion=1,0", match="decompression bomb"),
        blur("{in}/big.png", "--motion=1,0", match="memory budget"),
        blur("{in}/zerodims.png", "--motion=1,0", match="empty size"),
        blur("{in}/text.png", "--motion=1,0", match="image"),
        blur("{in}/missing.png", "--motion=1,0", match="not found"),
        blur("{in}/pngas.jpg", "--motion=1,0", match="jpeg"),
        blur("{in}/grey16.png", "--motion=3,0", code=0),
        blur("{in}/rgba.png", "--motion=3,0", code=0),
        blur("{in}/bilevel.tif", "--motion=3,0", match="dtype bool"),
        blur("{in}/bilevel.tif", "--motion=3,0", match="dtype bool", out="{out}/o.tif"),
        blur("{in}/float.tif", "--motion=3,0", match="float"),
        blur("{in}/float.tif", "--motion=3,0", code=0, out="{out}/o.tif"),
        blur("{in}/ünï cødé.png", "--motion=3,0", code=0, out="{out}/ü ø.png"),
        blur("{in}/with space.png", "--motion=3,0", code=0, out="{out}/with space.png"),
        blur("{in}/good.png", "--motion=1,0", out="{out}/o.xyz", match="extension"),
        blur("{in}/good.png", "--motion=1,0", out="{out}/noext", match="extension"),
        blur("{in}/good.png", "--motion=1,0", out="{in}", match="folder"),
        blur("{in}/good.png", "--motion=1,0", out="{out}/missing/o.png", match="folder"),
        blur("{in}/good.png", "--motion=1,0", out="{in}/good.png", match="overwrite"),
        blur("{in}/good.png", "--motion=1,0", out="{in}/sub/../good.png", match="overwrite"),
    ]
    return cases


def flow_psf_cases() -> list[Case]:
    g = "{in}/good.png"
    cases = [blur(g, "--flow", f"{{in}}/{kind}.{ext}", match="flow")
             for ext in ("npy", "flo") for kind in ("zero", "trunc", "magic")]
    for name in ("nan", "inf", "ninf", "shape3", "shape2d", "shape4d", "wrongsize", "empty",
                 "complex", "bool", "strings", "pickle"):
        cases.append(blur(g, "--flow", f"{{in}}/flow_{name}.npy", match="flow"))
    cases += [
        blur(g, "--flow", "{in}/flow_huge.npy", match="--samples"),
        blur(g, "--flow", "{in}/flow_huge.npy", "--samples", "4", code=0),
        blur(g, "--flow", "{in}/flow_huge1.npy", "--samples", "4", code=0),
        blur(g, "--flow", "{in}/flow_f16.npy", code=0),
        blur(g, "--flow", "{in}/flow_int.npy", code=0),
        blur(g, "--flow", "{in}/flow_fortran.npy", code=0),
        blur(g, "--flow", "{in}/flow ü.npy", code=0),
        blur(g, "--flow", "{in}/flow.flo", code=0),
        blur(g, "--flow", "{in}/flo_huge_dims.flo", match="flo"),
        blur(g, "--flow", "{in}/flo_neg_dims.flo", match="flo"),
        blur(g, "--flow", "{in}/flo_nan.flo", match="nan"),
        blur(g, "--motion=1e9,0", match="--samples"),
        blur(g, "--motion=nan,0", match="finite"),
        blur(g, "--motion=inf,1", match="finite"),
        blur(g, "--motion=1,2,3", match="dx,dy"),
        blur(g, "--motion=1e9,0", "--samples", "4", code=0),
    ]
    for name in ("nan", "neg", "zero", "3d", "1d", "long", "inf"):
        cases.append(blur(g, "--psf", f"{{in}}/psf_{name}.npy", match="psf"))
    cases += [blur(g, "--psf", f"{{in}}/{k}.npy", match="psf") for k in ("zero", "trunc")]
    cases.append(blur(g, "--psf", "{in}/zero.png", match="image"))
    cases.append(blur(g, "--psf", "{in}/psf.npy", code=0))
    cases += [  # another format under a flow's or depth's name; a folder where a file goes
        blur(g, "--flow", g, match="not a numpy .npy file"),
        blur(g, "--flow", "{in}/flow.npy", "--depth", g, match="depth"),
        blur(g, "--flow", "{in}/folder.npy", match="is a folder"),
        blur("{in}/folder.png", "--motion=1,0", match="is a folder"),
    ]
    return cases


def option_cases() -> list[Case]:
    g = "{in}/good.png"
    m = "--motion=2,0"
    cases = [blur(g, m, "--response", f"{{in}}/{kind}.json", match="response")
             for kind in ("zero", "trunc", "magic")]
    cases += [blur(g, m, "--response", f"{{in}}/{n}", match="response")
              for n in ("resp_notobject.json", "resp_unknown.json", "resp_nan.json",
                        "resp_deep.json", "resp_latin1.json", "resp_table_bad.json",
                        "missing.json")]
    cases += [
        blur(g, m, "--response", "{in}/resp.json", code=0),
        blur(g, m, "--response", "exp:abc", match="exp"),
        blur(g, m, "--response", "gamma:-2", match="positive"),
        blur(g, m, "--response", "nope", match="response"),
        blur(g, m, "--samples", "0", match="samples"),
        blur(g, m, "--samples", "-3", match="samples"),
        blur(g, m, "--saturation", "nan", match="saturation"),
        blur(g, m, "--saturation", "0.5", match="saturation"),
        blur(g, m, "--memory-budget", "0", match="memory budget"),
        blur(g, m, "--memory-budget", "lots", match="memory budget"),
        blur(g, m, "--memory-budget", "100", match="memory budget (100 B)"),
        blur(g, m, "--anchor", "middle", match="anchor"),
        blur(g, m, "--exposure", "trapezoid", match="exposure"),
        blur(g, "--psf", "{in}/psf.npy", "--exposure", "continuous", match="PSF"),
        blur(g, m, "--exposure", "continuous", code=0),
        Case("blur:device-9:9", ("blur", g, "{out}/o.png", m, "--device", "9:9"),
             match="9:9"),
        Case("blur:no-motion", ("blur", g, "{out}/o.png"), match="required"),
        Case("blur:two-motions", ("blur", g, "{out}/o.png", m, "--flow", "{in}/flow.npy"),
             match="not allowed"),
        Case("info", ("info",), code=0),
        # names longer than the file system takes (NAME_MAX 255): OSError tracebacks before
        blur(g, m, out="{out}/" + "y" * 300 + ".png", match="too long"),
        blur(g, m, "--response", "y" * 300 + ".json", match="too long"),
        Case("calibrate:long-name", ("calibrate", "{in}/" + "y" * 300, "-o", "{out}/c.json"),
             match="too long"),
        Case("video:long-name", ("video", "{in}/" + "y" * 300, "{out}/v"), match="too long"),
        Case("info:extra", ("info", "--verbose"), match="unrecognized"),
        Case("unknown-command", ("sharpen", g), match="invalid choice"),
        Case("demo:out-is-file", ("demo", "--out", "{in}/good.png", *NUMPY), match="folder"),
        Case("demo:device", ("demo", "--out", "{out}/d", "--device", "9:9"), match="9:9"),
    ]
    return cases


def batch(*extra: str, code: int = 2, match: str = "", src: str = "{in}/batchin",
          out: str = "{out}") -> Case:
    motion = () if any(e.startswith(("--motion", "--flow-dir", "--psf")) for e in extra) \
        else ("--motion=1,0",)
    return Case(f"batch:{src}:{' '.join(extra)}" + ("" if out == "{out}" else f"->{out}"),
                ("batch", src, out, "--quiet", *NUMPY, *motion, *extra), code, match)


def batch_cases() -> list[Case]:
    cases = [batch("--manifest", f"{{in}}/{n}", match=word) for n, word in (
        ("b_traversal_image.csv", "outside"), ("b_traversal_deep.csv", "outside"),
        ("b_absolute_image.csv", "outside"), ("b_output_up.csv", "file name"),
        ("b_output_dotdot.csv", "file name"), ("b_output_absolute.csv", "file name"),
        ("b_output_subdir.csv", "file name"), ("b_flow_out.csv", "outside"),
        ("b_flow_abs.csv", "outside"), ("b_flow_symlink.csv", "outside"),
        ("b_psf_out.csv", "outside"), ("b_response_out.csv", "outside"),
        ("b_nul.csv", "path"),
        ("b_unknown_col.csv", "unknown"), ("b_no_image_col.csv", "image"),
        ("b_twice.csv", "twice"), ("b_extra_cells.csv", "cells"), ("b_latin1.csv", "utf-8"),
        ("b_empty_name.csv", "empty"), ("b_long_name.csv", "too long"), ("zero.csv", "image"),
        ("magic.csv", "manifest"),
        ("missing.csv", "not found"))]
    cases += [
        batch("--manifest", "{in}/b_symlink_image.csv", src="{in}/symin", match="outside"),
        batch("--motion=2,0", src="{in}/symin", match="outside"),
        batch("--motion=1,0", src="{in}/seq", code=1),  # one zero-byte frame: reported
        batch("--manifest", "{in}/trunc.csv", code=0),  # cut after the header: no rows
        batch("--manifest", "{in}/b_unicode_ok.csv", code=0),
        batch("--manifest", "{in}/b_nested_ok.csv", code=0),
        batch("--motion=1,0", code=0),
        batch("--motion=1,0", out="{in}/good.png", match="not a folder"),
        batch("--motion=1,0", out="{in}/batchin", match="differ"),
        batch("--motion=1,0", src="{in}/nope", match="not found"),
        batch("--flow-dir", "{in}/nope", match="not found"),
        batch("--flow-dir", "{in}/symbflows", match="outside"),
        batch("--motion=1,0", "--scheduler", "local:0", match="local:n"),
        batch("--motion=1,0", "--response", "{in}/trunc.json", match="response"),
        batch("--psf", "{in}/missing.npy", match="not found"),
        batch("--motion=abc", match="dx,dy"),
    ]
    return cases


def bad_manifest_cases() -> list[Case]:
    study = [(n, w) for n, w in (
        ("m_pairs_empty.json", "non-empty"), ("m_pairs_traversal.json", "outside"),
        ("m_pairs_absolute.json", "outside"), ("m_pairs_symlink.json", "outside"),
        ("m_pairs_flow_out.json", "outside"), ("m_pairs_motion_text.json", "motion"),
        ("m_pairs_motion_nan.json", "motion"), ("m_pairs_two_forms.json", "exactly one"),
        ("m_pairs_path_number.json", "path"), ("m_pairs_not_list.json", "list"),
        ("m_kind.json", "kind"), ("m_stack_one.json", "2 frames"),
        ("m_stack_traversal.json", "outside"), ("zero.json", "manifest"),
        ("trunc.json", "manifest"), ("magic.json", "manifest"), ("resp_deep.json", "manifest"),
        ("missing.json", "not found"))]
    cases = [Case(f"study:{n}", ("study", f"{{in}}/{n}", "--report", "{out}/r.json",
                                 "--quiet"), match=w) for n, w in study]
    cases += [
        Case("study:report-folder-missing", ("study", "{in}/m_pairs_empty.json", "--report",
                                             "{out}/no/r.json", "--quiet"), match="folder"),
        Case("study:report-is-input", ("study", "{in}/m_kind.json", "--report",
                                       "{in}/m_kind.json", "--quiet"), match="overwrite"),
        Case("study:splits-zero", ("study", "{in}/m_kind.json", "--report", "{out}/r.json",
                                   "--splits", "0", "--quiet"), match="--splits"),
    ]
    study += [("m_pairs_motion_huge.json", "finite"), ("m_pairs_motion_bool.json", "number"),
              ("m_pairs_ratio_huge.json", "finite"), ("m_pairs_anchor_list.json", "anchor"),
              ("m_series_white.json", "saturated"), ("m_series_same_exposure.json", "same"),
              ("m_series_fnumber_some.json", "f-number"),
              ("m_series_darker.json", "not brighter"),
              ("m_pairs_motion_long.json", "too small for their motion")]
    cases += [Case(f"study:{n}", ("study", f"{{in}}/{n}", "--report", "{out}/r.json",
                                  "--quiet"), match=w) for n, w in study[-9:]]
    cases += [  # no output may replace an input, nor land in a folder of inputs
        Case("study:figures-in-inputs", ("study", "{in}/m_series_inputs.json", "--report",
                                         "{out}/r.json", "--figures", "{in}/series",
                                         "--quiet"), match="holds the input"),
        Case("calibrate:output-is-an-image", ("calibrate", "{in}/series", "--times",
                                              "{in}/times_twice.txt", "-o",
                                              "{in}/series/a.png"), match="overwrite"),
        Case("calibrate:manifest-output-is-an-image", ("calibrate",
                                                       "{in}/m_series_inputs.json", "-o",
                                                       "{in}/series/a.png"), match="overwrite"),
        Case("calibrate:report-in-inputs", ("calibrate", "{in}/m_series_inputs.json", "-o",
                                            "{out}/r.json", "--report", "{in}/series"),
             match="holds the input"),
        Case("calibrate:times-huge", ("calibrate", "{in}/series", "--times",
                                      "{in}/times_huge.txt", "-o", "{out}/r.json"),
             match="out of range"),
        Case("calibrate:times-name-twice", ("calibrate", "{in}/series", "--times",
                                            "{in}/times_twice.txt", "-o", "{out}/r.json"),
             match="more than once"),
    ]
    calib = [("m_series_huge.json", "finite"), ("m_series_bool.json", "number"),
             ("m_series_twice.json", "more than once"),
             ("m_series_empty.json", "non-empty"), ("m_series_traversal.json", "outside"),
             ("m_series_negative.json", "positive"), ("m_series_missing.json", "not found"),
             ("m_pairs_empty.json", "non-empty"), ("zero.json", "manifest"),
             ("symseries", "outside"), ("nope", "not found"),
             ("m_series_darker.json", "not brighter")]
    cases += [Case(f"calibrate:{n}", ("calibrate", f"{{in}}/{n}", "-o", "{out}/r.json",
                                      "--quiet"), match=w) for n, w in calib]
    cases += [
        Case("calibrate:output-folder-missing", ("calibrate", "{in}/m_series_negative.json",
                                                 "-o", "{out}/no/r.json"), match="folder"),
        Case("calibrate:output-is-folder", ("calibrate", "{in}/series", "-o", "{in}"),
             match="folder"),
        Case("calibrate:times-malformed", ("calibrate", "{in}/series", "--times",
                                           "{in}/series/times.txt", "-o", "{out}/r.json"),
             match="fast"),
        Case("calibrate:times-missing", ("calibrate", "{in}/series", "--times",
                                         "{in}/nope.txt", "-o", "{out}/r.json"),
             match="not found"),
    ]
    return cases


def video_cases() -> list[Case]:
    cases = [Case(f"video:{k}.mp4", ("video", f"{{in}}/{k}.mp4", "{out}/o.mp4", "--quiet",
                                     *NUMPY), match="video" if k != "trunc" else "",
                  needs_av=True, keeps_output=k == "trunc")
             for k in ("zero", "magic", "trunc")]
    cases += [
        Case("video:good", ("video", "{in}/good.mp4", "{out}/o.mp4", "--quiet", *NUMPY,
                            "--save-flows", "{out}/flows/"), code=0, needs_av=True),
        Case("video:fps", ("video", "{in}/seq", "{out}/v/", "--fps", "0", "--quiet"),
             match="fps"),
        Case("video:shutter", ("video", "{in}/seq", "{out}/v/", "--shutter", "400",
                               "--quiet"), match="shutter"),
        Case("video:symlinked-frame", ("video", "{in}/symseq", "{out}/v/", "--quiet",
                                       *NUMPY), match="outside"),
        Case("video:symlinked-flow", ("video", "{in}/seq", "{out}/v/", "--flow",
                                      "{in}/symflows", "--quiet", *NUMPY), match="outside"),
        Case("video:no-such-input", ("video", "{in}/nope.mp4", "{out}/o.mp4", "--quiet"),
             match="nope"),
        Case("video:save-flows-is-file", ("video", "{in}/seq", "{out}/v/", "--save-flows",
                                          "{in}/good.png", "--quiet"), match="not a folder"),
        Case("video:bad-response", ("video", "{in}/seq", "{out}/v/", "--response",
                                    "{in}/magic.json", "--quiet"), match="response"),
    ]
    return cases


def psf_estimation_cases() -> list[Case]:
    """``clblur psf`` and a blur pair's ``"psf": "estimate"``."""
    def psf(name: str, *args: str, match: str) -> Case:
        return Case(f"psf:{name}", ("psf", *args), match=match)

    g = "{in}/good.png"
    return [
        psf("too-small", g, g, "{out}/k.npy", match="at least 32 px"),
        psf("shapes-differ", g, "{in}/grey16.png", "{out}/k.npy", match="differ in shape"),
        psf("out-is-input", g, g, g, match="overwrite"),
        psf("out-extension", g, g, "{out}/k.jpg", match="extension"),
        psf("out-folder-missing", g, g, "{out}/no/k.npy", match="folder"),
        psf("size-text", g, g, "{out}/k.npy", "--size", "big", match="invalid int"),
        psf("response-bad", g, g, "{out}/k.npy", "--response", "gamma:x", match="gamma"),
        psf("missing", "{in}/nope.png", g, "{out}/k.npy", match="not found"),
        psf("not-an-image", "{in}/zero.json", g, "{out}/k.npy", match="image"),
        Case("study:m_pairs_psf_size.json", ("study", "{in}/m_pairs_psf_size.json", "--report",
                                             "{out}/r.json", "--quiet"), match="psf_size"),
        Case("study:m_pairs_estimate_shapes.json",
             ("study", "{in}/m_pairs_estimate_shapes.json", "--report", "{out}/r.json",
              "--quiet"), match="differ in shape"),
    ]


CASES = (image_cases() + flow_psf_cases() + option_cases() + batch_cases()
         + bad_manifest_cases() + video_cases() + psf_estimation_cases())


def test_corpus_is_large_and_distinct():
    ids = [c.id for c in CASES]
    assert len(set(ids)) == len(ids), "duplicate case"
    assert len(CASES) >= 80


# --------------------------------------------------------------------------- invariants
def snapshot(root: Path, skip: Path | None = None) -> dict[str, object]:
    """Every entry under ``root`` (except ``skip``): content hash, link target or 'dir'."""
    state = {}
    for dirpath, dirnames, filenames in os.walk(root):
        here = Path(dirpath)
        if skip is not None and (here == skip or skip in here.parents):
            dirnames[:] = []
            continue
        for name in dirnames + filenames:
            p = here / name
            if skip is not None and p == skip:
                continue
            if p.is_symlink():
                state[str(p)] = ("link", os.readlink(p))
            elif p.is_dir():
                state[str(p)] = "dir"
            else:
                state[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest()
    return state


def fill(arg: str, root: Path, out: Path) -> str:
    return arg.format(**{"in": str(root / "in"), "out": str(out),
                         "outside": str(root / "outside"), "root": str(root)})


def run_case(case: Case, root: Path, capfd) -> tuple[int, str, Path]:
    out = root / f"out_{abs(hash(case.id)):x}"
    out.mkdir(exist_ok=True)
    capfd.readouterr()
    code = main([fill(a, root, out) for a in case.argv])
    captured = capfd.readouterr()
    return code, captured.err, out


def check_invariants(case: Case, code: int, err: str, out: Path, before: dict, root: Path):
    assert "Traceback" not in err, err
    assert code == case.code, f"{case.id}: exit {code}, expected {case.code}; stderr: {err}"
    lines = [line for line in err.splitlines() if line.strip()]
    if code == 2:
        assert len(lines) == 1, f"{case.id}: expected one line on stderr, got {lines}"
        assert "error:" in lines[0]
        assert case.match.lower() in lines[0].lower(), f"{case.id}: {lines[0]}"
    assert snapshot(root, skip=out) == before, f"{case.id}: something outside OUT changed"
    written = [p for p in out.rglob("*") if p.is_file()]
    assert not [p for p in written if ".part" in p.name], f"{case.id}: partial files {written}"
    if code == 2 and not case.keeps_output:
        assert not [p for p in written if ".clblur-batch" not in p.parts], \
            f"{case.id}: output written on failure: {written}"


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_hostile_input(case: Case, corpus: Path, capfd, monkeypatch):
    if case.needs_av and av is None:
        pytest.skip("PyAV not installed")
    monkeypatch.chdir(corpus / "cwd")
    out = corpus / f"out_{abs(hash(case.id)):x}"
    before = snapshot(corpus, skip=out)
    code, err, out = run_case(case, corpus, capfd)
    check_invariants(case, code, err, out, before, corpus)


def test_traversal_manifest_leaves_the_outside_file_untouched(corpus: Path, capfd):
    """Issue 10's reproduction: ``../../src/x.png`` in the manifest of a batch."""
    src = corpus / "src"
    src.mkdir(exist_ok=True)
    victim = src / "x.png"
    victim.write_bytes((corpus / "in" / "good.png").read_bytes())
    stamp = victim.stat().st_mtime_ns
    out = corpus / "out_trav" / "a"
    out.parent.mkdir(exist_ok=True)
    (corpus / "out_trav" / "m.csv").write_text("image,dx,dy\n../../src/x.png,1,0\n")
    code = main(["batch", str(corpus / "in"), str(out), "--manifest",
                 str(corpus / "out_trav" / "m.csv"), "--quiet", *NUMPY])
    err = capfd.readouterr().err
    assert code == 2 and "outside" in err and len(err.strip().splitlines()) == 1
    assert victim.stat().st_mtime_ns == stamp
    assert not (src / ".clblur-batch").exists() and not out.exists()


# a few through a real process: the exit code and every byte on fd 2, C libraries included
SUBPROCESS = ["blur:{in}/trunc.jpg:--motion=1,0", "blur:{in}/bomb.png:--motion=1,0",
              "batch:{in}/batchin:--manifest {in}/b_traversal_deep.csv",
              "study:m_pairs_empty.json"]


@pytest.mark.parametrize("cid", SUBPROCESS)
def test_hostile_input_in_a_process(cid: str, corpus: Path):
    case = next(c for c in CASES if c.id == cid)
    out = corpus / "out_proc"
    out.mkdir(exist_ok=True)
    before = snapshot(corpus, skip=out)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[1]), "CLBLUR_QUIET": "1"}
    r = subprocess.run([sys.executable, "-m", "clblur.cli",
                        *[fill(a, corpus, out) for a in case.argv]],
                       capture_output=True, text=True, env=env, cwd=corpus / "cwd",
                       timeout=120)
    check_invariants(case, r.returncode, r.stderr, out, before, corpus)


# --------------------------------------------------------------------------- generated
CELLS = st.sampled_from([
    "good.png", "with space.png", "ünï cødé.png", "sub/nested.png", "missing.png",
    "../outside/victim.png", "../../outside/victim.png", "/etc/passwd", "link_out.png",
    "symin/escape.png", "./good.png", "sub/../good.png", "..", ".", "", "a\tb.png",
    "flow.npy", "../outside/victim.npy", "link_out.npy", "psf.npy", "resp.json",
    "../outside/victim.json", "exp:2", "srgb", "x" * 300 + ".png", "ü.png",
])
NUMBERS = st.sampled_from(["", "1", "-2.5", "nan", "inf", "1e9", "abc", "0"])


@st.composite
def manifests(draw) -> str:
    columns = draw(st.lists(st.sampled_from(["output", "dx", "dy", "flow", "psf", "response",
                                             "samples"]), unique=True, max_size=4))
    columns = ["image", *columns]
    rows = []
    for _ in range(draw(st.integers(1, 3))):
        row = []
        for c in columns:
            cell = draw(NUMBERS if c in ("dx", "dy", "samples") else CELLS)
            if "," in cell or '"' in cell:
                cell = '"' + cell.replace('"', '""') + '"'
            row.append(cell)
        rows.append(",".join(row))
    return "\n".join([",".join(columns), *rows]) + "\n"


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=manifests())
def test_generated_manifests_keep_the_invariants(text: str, corpus: Path, capfd):
    work = corpus / "gen"
    work.mkdir(exist_ok=True)
    manifest = corpus / "in" / "gen.csv"  # inside IN_DIR, so relative cells resolve there
    before_inputs = snapshot(corpus / "in")
    manifest.write_text(text)
    out = work / "out"
    before = snapshot(corpus, skip=work)
    capfd.readouterr()
    try:
        code = main(["batch", str(corpus / "in" / "seq"), str(out), "--manifest",
                     str(manifest), "--motion=1,0", "--samples", "3", "--quiet", *NUMPY])
        err = capfd.readouterr().err
        assert "Traceback" not in err and code in (0, 1, 2), (code, err)
        if code == 2:
            assert len(err.strip().splitlines()) == 1, err
        assert snapshot(corpus, skip=work) == before, "something outside OUT changed"
        written = [p for p in out.rglob("*") if p.is_file()] if out.exists() else []
        assert not [p for p in written if ".part" in p.name]
        if code == 2:
            assert not written, written
        for p in written:  # every output lies inside OUT once symlinks are resolved
            assert p.resolve().is_relative_to(out.resolve())
    finally:
        manifest.unlink()
        import shutil

        shutil.rmtree(work, ignore_errors=True)
    assert snapshot(corpus / "in") == before_inputs
