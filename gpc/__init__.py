"""gpc: Generative Predictive Control for frozen diffusion policies.

The repository's folders install under this one namespace: ``gpc.datasets`` (Zarr episode
stores), ``gpc.models`` (networks, policy, world models, rewards, planners, training),
``gpc.tasks`` (environments, experts, task geometry), ``gpc.harness`` (closed-loop
evaluation, collection, paired statistics) and ``gpc.cli`` (the ``gpc`` command).
"""

__version__ = "0.1.0"
