"""Networks drlyap did not build, held as data and run by an interpreter whose operations also run on enclosures,
so that an imported controller or certificate gets the same proofs as a drlyap pair.

* :mod:`~drlyap.graph.interpreter` -- :class:`Graph` (forward, reverse-mode ``value_and_grad``), :class:`GraphBuilder`;
* :mod:`~drlyap.graph.passes` -- rewrites that are identities in real arithmetic (:func:`simplify`);
* :mod:`~drlyap.graph.prefix` -- the input prefix ``x - x*`` with the angle wrap, recognised and removed;
* :mod:`~drlyap.graph.from_onnx` -- :func:`read_onnx`: an ONNX file, parsed as data, into a :class:`Graph`.
"""

from drlyap.graph.from_onnx import SUPPORTED, read_onnx
from drlyap.graph.interpreter import INPUT, OPS, Graph, GraphBuilder, Node
from drlyap.graph.passes import simplify

__all__ = ["INPUT", "OPS", "SUPPORTED", "Graph", "GraphBuilder", "Node", "read_onnx", "simplify"]
