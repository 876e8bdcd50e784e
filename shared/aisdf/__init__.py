"""AiSDF: online Atlanta-world-aware neural signed distance fields for indoor robots.

The library every service imports: wire protocol, configuration, geometry, the SDF
network and its training, synthetic buildings, dataset readers and the planner client.
"""

__version__ = "0.1.0"
