"""The case room: a plan's settings, its scene and the steering search over template holes."""
