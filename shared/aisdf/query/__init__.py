"""The query engine without Zenoh: the latest map, the answer planners are served
(``answer.served_answer``), its background bake, and meshes. ``aisdf-query`` wires it to
the network; the benchmarks and the tests drive it in-process."""
