import importlib.metadata as _metadata

from ._allocator import retain_freed_memory as retain_freed_memory
from ._batch import (
    batch_mesh as batch_mesh,
    fit_batch as fit_batch,
    render_batch as render_batch,
    shard_batch as shard_batch,
)
from ._chart import (
    Chart as Chart,
    ChartCalibration as ChartCalibration,
    ChartError as ChartError,
    ChartPose as ChartPose,
    ChartView as ChartView,
    calibrate as calibrate,
    chart_scene as chart_scene,
    detect_chart as detect_chart,
    make_chart as make_chart,
    read_chart as read_chart,
    write_chart as write_chart,
)
from ._compiled import enable_compilation_cache as enable_compilation_cache
from ._corrections import (
    depth_edges as depth_edges,
    edge_weight as edge_weight,
    footprint_prefilter as footprint_prefilter,
)
from ._exif import ExifLens as ExifLens, read_exif as read_exif
from ._filters import (
    AbstractMethod as AbstractMethod,
    Aperture as Aperture,
    Auto as Auto,
    Hard as Hard,
    Jitter as Jitter,
    Layered as Layered,
    LocalOcclusion as LocalOcclusion,
    Occlusion as Occlusion,
    Soft as Soft,
    Supersample as Supersample,
    choose_method as choose_method,
    coc_filter as coc_filter,
)
from ._fit import (
    RESULTS as RESULTS,
    AbstractForwardModel as AbstractForwardModel,
    DefocusModel as DefocusModel,
    FitResult as FitResult,
    fit_lens as fit_lens,
    solve_lens as solve_lens,
)
from ._holes import depth_holes as depth_holes, fill_depth_holes as fill_depth_holes
from ._lens import (
    ThinLens as ThinLens,
    coc_radius as coc_radius,
    linearize_depth as linearize_depth,
    signed_coc_radius as signed_coc_radius,
)
from ._overlap import circle_pixel_overlap as circle_pixel_overlap
from ._raytrace import (
    lens_from_raytracer as lens_from_raytracer,
    ray_distance_to_z as ray_distance_to_z,
)
from ._render import render as render
from ._scene import Treatment as Treatment, scene_treatment as scene_treatment
from ._upsample import upsample_depth as upsample_depth


try:
    __version__ = _metadata.version("jaxdof")
except _metadata.PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0"
