"""All file input and output: images (with header probing and decode limits), rasters read
window by window (TIFF, ``.npy``), flows, PSFs, video, atomic writes and the rules on where
paths may point.

===================  ==============================================================
module               holds
===================  ==============================================================
``io.images``        ``read_image``/``write_image`` (dispatch by ``image_format``),
                     ``probe_image``/``check_decodable`` (header only, bomb check),
                     ``exr_layout`` (what an EXR output keeps of its input),
                     ``codec_block`` (a lossy codec's block size, from the header)
``io.raster``        ``MappedRaster``, ``TiffWindows``, ``OrientedRaster``, ``open_image``
                     (window by window), ``create_tiff``
``io.flows``         ``.npy``/``.flo`` flows (``read_flow``, ``open_flow``), ``read_psf``
``io.atomic``        ``atomic_write`` (temp file + rename)
``io.paths``         ``resolve_inside``, ``check_output``, ``refuse_overwrite``,
                     ``require_file``
``io.video``         video files and image sequences, frame by frame (PyAV; imported on
                     use, not by ``clblur.io``)
===================  ==============================================================
"""

from clblur.io.atomic import atomic_write, atomic_write_text, tmp_beside
from clblur.io.flows import FLO_MAGIC, open_flow, read_depth, read_flow, read_psf, write_flow
from clblur.io.images import (
    IMAGE_FORMATS,
    check_decodable,
    codec_block,
    describe_size,
    exr_layout,
    image_format,
    light_channels,
    probe_image,
    read_image,
    response_for_file,
    write_image,
)
from clblur.io.paths import (
    check_output,
    data_dir,
    gopro_frames,
    refuse_overwrite,
    require_file,
    resolve_inside,
)
from clblur.io.raster import (
    MappedRaster,
    OrientedRaster,
    TiffWindows,
    as_array_like,
    create_tiff,
    is_tiff,
    open_image,
)

__all__ = ["FLO_MAGIC", "IMAGE_FORMATS", "MappedRaster", "OrientedRaster", "TiffWindows",
           "as_array_like", "atomic_write", "atomic_write_text", "check_decodable", "codec_block",
           "check_output", "create_tiff", "data_dir", "describe_size", "exr_layout", "gopro_frames",
           "image_format", "is_tiff", "light_channels", "open_flow", "open_image", "probe_image",
           "read_flow", "read_depth", "read_image", "read_psf", "refuse_overwrite",
           "require_file", "resolve_inside", "response_for_file", "tmp_beside", "write_flow",
           "write_image"]
