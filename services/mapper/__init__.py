"""AiSDF mapper service: trains the SDF continually from keyframes and publishes the map."""
