"""Event graphs: the graph settings, the causal radius graph (batch and streaming), voxel pooling, dense maps."""
from dagr_lite.graph.pool import PooledGraph, recency_maps, to_dense, voxel_max_pool
from dagr_lite.graph.radius import radius_graph
from dagr_lite.graph.spec import EventGraphSpec
from dagr_lite.graph.streaming import StreamingGraph

__all__ = ["EventGraphSpec", "PooledGraph", "StreamingGraph", "radius_graph", "recency_maps", "to_dense",
           "voxel_max_pool"]
