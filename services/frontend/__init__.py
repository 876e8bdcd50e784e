"""AiSDF frontend service: streams a posed depth source, selects keyframes, publishes them."""
