"""gonio.capture: cameras, RAW linearisation, HDR, fiducials, calibration, sessions, reduction."""
