"""Serving a controller over the network (`gpc serve`): the wire format (``wire``, torch-free) and the server.

The robot-side client is ``gpc.client``; it imports ``gpc.serving.wire`` and nothing that needs torch.
"""
