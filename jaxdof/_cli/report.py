"""What the CLI prints: a fit as text or JSON, a file's `info`, the EXIF a fit starts from, and
the demo's table (the progress while it works: `progress`)."""

from __future__ import annotations

import json
import sys
import types

import numpy as np

from .._io import SUBSAMPLED
from .parse import FIELDS


def note(msg: str) -> None:
    """A remark for the user (a decoding note, a file written): stderr, keeping stdout clean."""
    print(msg, file=sys.stderr)


# ----------------------------------------------------------------------------------------------
# A fit's result


def _stderr_dict(stderr: dict, index: int | None) -> dict:
    out = {}
    for name, v in stderr.items():
        v = np.asarray(v)
        v = v if v.ndim == 0 or index is None else v.reshape(-1)[min(index, v.size - 1)]
        out[name] = float(f"{float(v):.4g}") if np.isfinite(v) else None
    return out


def fit_summary(result) -> dict:
    """The `fit --json` object of a `FitResult` (`FitResult.to_dict()`); the text output reads
    it too: lens 0's fields, `stderr`, `focus_power` and `focus_power_stderr` at the top level (a
    single photo's fit reads as one lens), then `success`, `status`, `message`, `steps`, `loss`,
    `sigma`, `condition`, `max_radius`, `pixels_used`, `border`, `levels`, `treatment`, `adequacy` (the
    model-adequacy test), `stderr_kind`, `names`, `covariance`, `gain`, `offset`, and `lenses`
    with one entry per photo. SI units; a value that is not finite (a standard error the data
    cannot determine, a focus distance at infinity) is `null`.
    """
    return result.to_dict()


def _adequacy_line(summary: dict) -> str | None:
    """The model check's verdict and what the standard errors are, in words."""
    test = summary.get("adequacy")
    if not test or test.get("p_value") is None:
        return None
    verdict = "consistent" if test["adequate"] else "INCONSISTENT"
    kind = summary.get("stderr_kind", "noise")
    if kind == "tile spread":
        kind = f"tile spread (noise x {test['inflation']:.3g})"
    return (
        f"model check: {verdict} (p = {test['p_value']:.3g}, {test['tiles']:g} tiles); "
        f"standard errors: {kind}"
    )


def format_value(name: str, v, err=None) -> str:
    """`v` (SI) in the unit a photographer reads (mm, m), with `± err` when it is known.

    `None` is a value JSON cannot hold, infinity (a focus distance at infinity): `inf`."""
    v = np.inf if v is None else v
    if name in ("focal_length", "focus_distance", "pixel_pitch"):
        scale, unit = (1e3, "mm") if name != "focus_distance" else (1.0, "m")
        s = f"{v * scale:.5g} {unit}"
        return s + (f" ± {err * scale:.2g}" if err is not None else "")
    return f"{v:.5g}" + (f" ± {err:.2g}" if err is not None else "")


def print_fit(
    summary: dict, target_names: list[str], free, *, as_json: bool, pixels: int | None = None
) -> None:
    """A `fit_summary` on stdout: one JSON object, or a block per lens, the pixels fitted (of
    `pixels`, the photos' total, when given), the model check and what the standard errors are,
    and a verdict line (with the status's name when the fit failed)."""
    if as_json:
        print(json.dumps(summary, indent=2))
        return
    several = len(summary["lenses"]) > 1
    for name_of_target, lens in zip(target_names, summary["lenses"]):
        print((f"target {name_of_target}" if several else "recovered lens") + ":")
        for name in FIELDS:
            state = "" if name in free else "  (held)"
            value = format_value(name, lens[name], lens["stderr"].get(name))
            print(f"  {name:15s} {value}{state}")
    of = f" of {pixels}" if pixels is not None else ""
    print(f"pixels used {summary['pixels_used']}{of} (border {summary['border']} px)")
    if summary.get("treatment"):
        print(f"treatment: {summary['treatment']['text']}")
    for name, entry in (summary.get("nuisances") or {}).items():
        print(f"{name}: {entry['text']}")
    line = _adequacy_line(summary)
    if line is not None:
        print(line)
    status = summary["status"]
    if summary["success"] and status == "inconsistent":
        verdict = "converged, standard errors inflated to the tiles' spread"
    elif summary["success"]:
        verdict = "converged"
    elif status == "max_steps":
        verdict = "did NOT converge (max_steps)"
    else:
        verdict = f"FAILED ({status})"
    loss = summary["loss"]
    print(
        f"{verdict} after {summary['steps']} steps, "
        f"loss {'nan' if loss is None else format(loss, '.4g')}: {summary['message']}"
    )


# ----------------------------------------------------------------------------------------------
# EXIF and `info`


def _mm(metres: float) -> str:
    return f"{metres * 1e3:.4g} mm"


def _camera(exif) -> str:
    """`Make Model, lens LensModel` as far as known (`Model` often repeats `Make`)."""
    make, model = exif.make or "", exif.model or ""
    name = model if make and model.lower().startswith(make.lower()) else f"{make} {model}".strip()
    lens = f"lens {exif.lens_model}" if exif.lens_model else ""
    return ", ".join(x for x in (name, lens) if x)


def _sensor_source(exif) -> str:
    return (
        "the focal-plane resolution"
        if exif.pixel_pitch is not None
        else "the 35 mm-equivalent focal length"
    )


def exif_line(path: str, exif, read: dict, used: list[str], overridden: list[str], free) -> str:
    """`fit`'s one stderr line on the first TARGET's EXIF: the values read, which of them start
    the fit, and which the command line overrides (`read`: the usable values, SI)."""
    parts = []
    if "focal_length" in read:
        equivalent = exif.focal_length_35mm
        parts.append(
            f"focal length {_mm(read['focal_length'])}"
            + (f" (35 mm equivalent {_mm(equivalent)})" if equivalent else "")
        )
    if "f_number" in read:
        parts.append(f"f/{read['f_number']:.3g}")
    if "focus_distance" in read:
        parts.append(f"focus {format_value('focus_distance', read['focus_distance'])}")
    if "sensor_width" in read:
        parts.append(f"sensor width {_mm(read['sensor_width'])} (from {_sensor_source(exif)})")
    camera = _camera(exif)
    head = f"{path}: EXIF" + (f" {camera}" if camera else "") + ": "
    if not parts:
        return head + "no focal length, f-number, focus distance or sensor size to start from"
    tail = []
    if used:
        names = ", ".join("f-number" if n == "f_number" else n.replace("_", " ") for n in used)
        held = ""
        if "focal_length" in used:
            held = " (focal length free)" if "focal_length" in free else " (focal length held)"
        tail.append(f"the fit starts from its {names}{held}")
    if overridden:
        options = {
            "focal_length": "--focal-length",
            "f_number": "--f-number",
            "focus_distance": "--focus",
            "sensor_width": "--sensor-width",
        }
        tail.append("overridden by " + ", ".join(options[n] for n in overridden))
    return head + ", ".join(parts) + "; " + "; ".join(tail)


def print_info(info: dict, *, as_json: bool) -> None:
    """`info`'s object (`commands.describe`) on stdout: one JSON object, or a few lines."""
    if as_json:
        print(json.dumps(info, indent=2))
        return
    bits = f"{info['bits']}-bit {'float' if info['dtype'].startswith('float') else 'integer'}"
    print(
        f"{info['file']}: {info['format']}, {info['width']} x {info['height']} pixels (W x H), "
        f"{info['channels']} channel{'s' if info['channels'] > 1 else ''} ({info['colour']}), "
        f"{info['dtype']} ({bits})"
    )
    encoding = {
        "sRGB": "sRGB: decoded to linear light when read (--linear takes it as linear)",
        "linear": "linear light, as stored",
        "unsupported": f"{info['dtype']} pixels are not read (8/16-bit integers or floats)",
    }[info["encoding"]]
    print(f"  {'encoding':16s}{encoding}" + ("; alpha ignored" if info["alpha"] else ""))
    if info.get("jpeg"):
        j = info["jpeg"]
        table = "the camera's own table" if j["quality"] is None else f"quality {j['quality']}"
        if j["chroma"] in SUBSAMPLED:  # what `fit --luma auto` reads from the header
            how = (
                f"colour {j['chroma']}: fit compares the luma in its 8 x 8 blocks (--luma, --jpeg)"
            )
        else:
            how = "grey" if j["chroma"] is None else f"colour {j['chroma']} (full resolution)"
        print(f"  {'JPEG':16s}{table}, {how}")
    exif = info["exif"]
    if exif is None:
        print(f"  {'EXIF':16s}none (no lens fields)")
        return
    camera = _camera(types.SimpleNamespace(**exif))
    print(f"  {'EXIF':16s}{camera or 'no camera name'}")

    def field(label: str, text: str | None) -> None:
        print(f"  {label:16s}{text if text is not None else 'not recorded'}")

    f, f35 = exif["focal_length"], exif["focal_length_35mm"]
    focal = None if f is None else _mm(f) + (f" (35 mm equivalent {_mm(f35)})" if f35 else "")
    field("focal length", focal if f is not None or f35 is None else f"35 mm equivalent {_mm(f35)}")
    field("f-number", None if exif["f_number"] is None else f"{exif['f_number']:.3g}")
    power = exif["focus_power"]
    field(
        "focus distance",
        None if power is None else format_value("focus_distance", exif["focus_distance"]),
    )
    pitch = exif["pixel_pitch"]
    field("pixel pitch", None if pitch is None else f"{pitch * 1e6:.4g} µm")
    width = exif["sensor_width"]
    source = _sensor_source(types.SimpleNamespace(**exif))
    field("sensor width", None if width is None else f"{_mm(width)} (from {source})")


# ----------------------------------------------------------------------------------------------
# The demo


def print_demo(truth, start, result) -> None:
    """The demo's table: truth, start and recovered value (± standard error) of each field."""
    err = _stderr_dict(result.stderr, None)
    print(f"{'':16s}{'truth':>12s}{'start':>12s}{'recovered':>24s}")
    for name in FIELDS:
        t, s, r = (float(np.asarray(getattr(x, name))) for x in (truth, start, result.lens))
        print(
            f"  {name:14s}{format_value(name, t):>12s}{format_value(name, s):>12s}"
            f"{format_value(name, r, err.get(name)):>24s}" + ("" if name in err else "  (held)")
        )
    verdict = "converged" if result.success else "did NOT converge"
    print(f"{verdict} in {int(result.num_steps)} steps, loss {float(result.loss):.3g}")
