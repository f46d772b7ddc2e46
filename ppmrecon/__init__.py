"""ppmrecon: multi-bandwidth progressive photon mapping on Mitsuba 3 and a consistent
learned post-reconstruction (Choi & Moon 2021)."""

__version__ = "0.1.0"
