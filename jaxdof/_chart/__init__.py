"""Calibration from a printed (or displayed) chart: its design and files (`_design`, `_files`),
finding it in a photo (`_detect`), its plane in the camera (`_geometry`), and the fit
(`_calibrate`). A chart is another source of the all-in-focus image and depth map that
`jaxdof.fit_lens` takes."""

from ._calibrate import ChartCalibration as ChartCalibration, calibrate as calibrate
from ._design import Chart as Chart, make_chart as make_chart
from ._detect import ChartView as ChartView, detect_chart as detect_chart
from ._files import read_chart as read_chart, write_chart as write_chart
from ._geometry import (
    ChartError as ChartError,
    ChartPose as ChartPose,
    camera_matrix as camera_matrix,
    chart_pose as chart_pose,
    chart_scene as chart_scene,
    focal_from_homographies as focal_from_homographies,
)
