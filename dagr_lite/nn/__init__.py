"""Network layers: the causal sparse GCN, and the branches built from it."""
from dagr_lite.nn.event_branch import EventBranch, GCNBlock
from dagr_lite.nn.gcn import GCNConv, GraphOperator, gcn_norm

__all__ = ["EventBranch", "GCNBlock", "GCNConv", "GraphOperator", "gcn_norm"]
