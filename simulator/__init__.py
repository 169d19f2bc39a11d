"""gonio.simulator: scene, renderer, sensor and DNG writer, virtual servo bus, simulated camera."""
