"""AiSDF query service: answers planners' SDF batches and mesh requests from the latest map."""
