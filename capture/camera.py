"""Cameras: the core's interface, a registry of real backends, and the gphoto2 backend.

The session only ever calls :class:`Camera` (``describe``, ``capture``, ``close``; defined
with :class:`Shot`, :class:`CameraInfo`, :class:`Light` and :class:`TargetChanger` in
:mod:`gonio.devices` and re-exported here), so a tethered DSLR (``gphoto2``) and the
rendered rig (the simulator's ``SimulatedRigCamera``, which the composition root
``gonio.app`` builds) are interchangeable.  Real backends are looked up by name in
:data:`CAMERA_BACKENDS` (``open_camera("gphoto2")``), colour-science style.

The gphoto2 backend drives the camera through libgphoto2's configuration widgets
(``shutterspeed``, ``f-number``/``aperture``, ``iso``, ``imageformat``), picks the nearest
value the camera offers (and reports the value actually used, since cameras only have
discrete steps), captures, and downloads the file byte for byte.  python-gphoto2 is the
optional extra ``camera`` (``pip install gonio[camera]``).
"""

from __future__ import annotations

import importlib
import math
import re
from typing import Any

from gonio.devices import Camera, CameraInfo, Light, Shot, TargetChanger
from gonio.errors import CameraError, UnknownNameError

__all__ = [
    "CAMERA_BACKENDS",
    "Camera",
    "CameraInfo",
    "GPhoto2Camera",
    "Light",
    "Shot",
    "TargetChanger",
    "open_camera",
    "parse_f_number",
    "parse_iso",
    "parse_shutter_speed",
]

#: File suffixes of RAW formats (the session refuses anything else from a real camera).
RAW_SUFFIXES = frozenset(
    {
        ".dng",
        ".nef",
        ".nrw",
        ".cr2",
        ".cr3",
        ".arw",
        ".srf",
        ".sr2",
        ".raf",
        ".orf",
        ".rw2",
        ".pef",
        ".srw",
        ".3fr",
        ".iiq",
        ".x3f",
        ".erf",
        ".kdc",
        ".mrw",
        ".raw",
    }
)


#: Backend name -> ``"module:factory"``; factories take keyword arguments.  The
#: ``simulated`` camera is not here: it belongs to the simulator, and only the
#: composition root (``gonio.app.devices``) wires it into a session.
CAMERA_BACKENDS: dict[str, str] = {
    "gphoto2": "gonio.capture.camera:GPhoto2Camera",
}


def open_camera(backend: str, **kwargs: Any) -> Camera:
    """Open a camera by backend name.

    Parameters
    ----------
    backend
        ``"gphoto2"`` (see :data:`CAMERA_BACKENDS`).
    **kwargs
        Passed to the backend (e.g. ``port=`` for ``gphoto2``).

    Raises
    ------
    UnknownNameError
        For an unknown backend name.
    CameraError
        When the backend cannot open a camera.
    """
    try:
        target = CAMERA_BACKENDS[backend]
    except KeyError:
        raise UnknownNameError(
            f"unknown camera backend {backend!r}; expected one of {sorted(CAMERA_BACKENDS)}"
        ) from None
    module, attr = target.split(":")
    return getattr(importlib.import_module(module), attr)(**kwargs)


# --------------------------------------------------------------------------------------
# Parsing the strings cameras use for their settings


def parse_shutter_speed(text: str) -> float:
    """Seconds from a camera's shutter-speed string (``"1/250"``, ``"0.0100s"``, ``"2\\""``).

    Returns NaN for non-numeric values such as ``"bulb"``.
    """
    t = text.strip().lower().rstrip("s").replace('"', "").replace("sec", "").strip()
    m = re.fullmatch(r"(\d+(?:\.\d*)?)\s*/\s*(\d+(?:\.\d*)?)", t)
    if m:
        return float(m.group(1)) / float(m.group(2))
    try:
        return float(t)
    except ValueError:
        return math.nan


def parse_f_number(text: str) -> float:
    """f-number from ``"f/8"``, ``"F8.0"`` or ``"8"`` (NaN if not numeric)."""
    t = text.strip().lower().removeprefix("f/").removeprefix("f").strip()
    try:
        return float(t)
    except ValueError:
        return math.nan


def parse_iso(text: str) -> float:
    """ISO speed from ``"100"`` or ``"ISO 100"`` (NaN for ``"Auto"``)."""
    t = text.strip().lower().removeprefix("iso").strip()
    try:
        return float(t)
    except ValueError:
        return math.nan


def nearest_choice(choices: list[str], value: float, parse) -> tuple[str, float]:
    """The choice whose parsed value is nearest to ``value`` in log scale."""
    best: tuple[float, str, float] | None = None
    for c in choices:
        v = parse(c)
        if not (v > 0 and math.isfinite(v)):
            continue
        d = abs(math.log(v / value))
        if best is None or d < best[0]:
            best = (d, c, v)
    if best is None:
        raise ValueError("no numeric choice")
    return best[1], best[2]


# --------------------------------------------------------------------------------------
# gphoto2


class GPhoto2Camera:
    """A tethered camera through libgphoto2 (python-gphoto2).

    Parameters
    ----------
    port
        libgphoto2 port (``"usb:001,004"``); the first camera found when None.
    require_raw
        Refuse a frame whose file is not a RAW format (a camera left on JPEG would
        otherwise silently ruin a session).
    max_rel_error
        Largest relative difference between a requested setting and the nearest value the
        camera offers before the request is refused (0.5 allows about half a stop).

    Raises
    ------
    CameraError
        python-gphoto2 is not installed, no camera is connected, or it cannot be opened.
    """

    #: Widget names tried for each setting, most common first.
    WIDGETS = {
        "exposure_time": ("shutterspeed", "shutterspeed2", "exposuretime"),
        "f_number": ("f-number", "aperture", "fnumber"),
        "iso": ("iso", "isospeed", "iso speed"),
    }
    PARSERS = {"exposure_time": parse_shutter_speed, "f_number": parse_f_number, "iso": parse_iso}

    def __init__(
        self, port: str | None = None, *, require_raw: bool = True, max_rel_error: float = 0.5
    ) -> None:
        try:
            import gphoto2 as gp
        except ImportError:
            raise CameraError(
                "the gphoto2 camera backend needs python-gphoto2: pip install 'gonio[camera]'"
            ) from None
        self._gp = gp
        self.require_raw = require_raw
        self.max_rel_error = max_rel_error
        self._cam = gp.Camera()
        try:
            if port is not None:
                plist = gp.PortInfoList()
                plist.load()
                self._cam.set_port_info(plist[plist.lookup_path(port)])
            self._cam.init()
        except gp.GPhoto2Error as exc:
            raise CameraError(self._explain(exc, "opening the camera")) from None
        self._closed = False
        self._model = self._read_model()
        self.port = port

    # -- helpers ----------------------------------------------------------------------
    def _explain(self, exc: Exception, doing: str) -> str:
        gp = self._gp
        code = getattr(exc, "code", None)
        if code in (gp.GP_ERROR_MODEL_NOT_FOUND, gp.GP_ERROR_IO_USB_FIND):
            return f"no camera found while {doing}: is it connected, switched on and not mounted?"
        if code in (gp.GP_ERROR_IO, gp.GP_ERROR_IO_USB_CLAIM, gp.GP_ERROR_CAMERA_BUSY):
            return f"camera not responding while {doing} ({exc}): check the cable and power"
        return f"camera failed while {doing} ({exc}): is it still connected and switched on?"

    def _read_model(self) -> str:
        try:
            return str(self._cam.get_abilities().model)
        except self._gp.GPhoto2Error:
            return "unknown gphoto2 camera"

    def _find_widget(self, config, setting: str):
        for name in self.WIDGETS[setting]:
            try:
                return config.get_child_by_name(name)
            except self._gp.GPhoto2Error:
                continue
        return None

    def _set(self, config, setting: str, value: float) -> tuple[str, float]:
        gp = self._gp
        widget = self._find_widget(config, setting)
        if widget is None:
            raise CameraError(
                f"camera {self._model!r} has no {setting} setting (looked for widgets "
                f"{list(self.WIDGETS[setting])}); leave {setting} unset or set it on the camera"
            )
        if widget.get_type() not in (gp.GP_WIDGET_RADIO, gp.GP_WIDGET_MENU):
            raise CameraError(f"camera {self._model!r}: {widget.get_name()} is not a choice widget")
        choices = [widget.get_choice(i) for i in range(widget.count_choices())]
        try:
            text, got = nearest_choice(choices, value, self.PARSERS[setting])
        except ValueError:
            raise CameraError(
                f"camera {self._model!r}: {widget.get_name()} offers no numeric values ({choices})"
            ) from None
        if (
            abs(got / value - 1.0) > self.max_rel_error
            and abs(value / got - 1.0) > self.max_rel_error
        ):
            raise CameraError(
                f"camera {self._model!r} does not support {setting} = {value:g}: the nearest "
                f"of {widget.get_name()} {choices} is {text!r}"
            )
        widget.set_value(text)
        return text, got

    def _prefer_raw(self, config) -> None:
        for name in ("imageformat", "imagequality", "imageformatsd"):
            try:
                w = config.get_child_by_name(name)
            except self._gp.GPhoto2Error:
                continue
            choices = [w.get_choice(i) for i in range(w.count_choices())]
            raw = [c for c in choices if "raw" in c.lower() or "nef" in c.lower()]
            if raw:
                # "RAW" alone beats "RAW + JPEG": one file per shot.
                w.set_value(min(raw, key=len))
            return

    # -- Camera interface ---------------------------------------------------------------
    def describe(self) -> CameraInfo:
        """Model and current settings."""
        settings: dict[str, Any] = {}
        try:
            config = self._cam.get_config()
            for setting in self.WIDGETS:
                w = self._find_widget(config, setting)
                if w is not None:
                    settings[setting] = w.get_value()
        except self._gp.GPhoto2Error as exc:
            raise CameraError(self._explain(exc, "reading the settings")) from None
        return CameraInfo("gphoto2", self._model, None, settings)

    def capture(self, exposure_time: float, iso: float | None, f_number: float | None) -> Shot:
        """Set exposure time (s), ISO and f-number (None keeps the camera's), shoot, and
        download the file.

        Raises
        ------
        CameraError
            Camera gone, setting unsupported, or the file is not RAW (``require_raw``).
        """
        gp = self._gp
        if self._closed:
            raise CameraError("camera is closed")
        try:
            config = self._cam.get_config()
            used: dict[str, float] = {}
            _, used["exposure_time"] = self._set(config, "exposure_time", exposure_time)
            if f_number is not None:
                _, used["f_number"] = self._set(config, "f_number", f_number)
            if iso is not None:
                _, used["iso"] = self._set(config, "iso", iso)
            if self.require_raw:
                self._prefer_raw(config)
            self._cam.set_config(config)
            path = self._cam.capture(gp.GP_CAPTURE_IMAGE)
            cfile = self._cam.file_get(path.folder, path.name, gp.GP_FILE_TYPE_NORMAL)
            data = bytes(memoryview(cfile.get_data_and_size()))
        except gp.GPhoto2Error as exc:
            raise CameraError(self._explain(exc, "capturing")) from None
        suffix = ("." + path.name.rsplit(".", 1)[-1].lower()) if "." in path.name else ""
        if self.require_raw and suffix not in RAW_SUFFIXES:
            raise CameraError(
                f"camera {self._model!r} delivered {path.name!r}, not a RAW file: set its image "
                "format to RAW"
            )
        if not data:
            raise CameraError(f"camera {self._model!r} delivered an empty file {path.name!r}")
        return Shot(
            data=data,
            suffix=suffix,
            exposure_time=used["exposure_time"],
            iso=used.get("iso", math.nan),
            f_number=used.get("f_number", math.nan),
            extra={"camera_file": f"{path.folder}/{path.name}"},
        )

    def close(self) -> None:
        """Release the camera (idempotent)."""
        if not self._closed:
            self._closed = True
            try:
                self._cam.exit()
            except self._gp.GPhoto2Error:
                pass

    def __enter__(self) -> GPhoto2Camera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
