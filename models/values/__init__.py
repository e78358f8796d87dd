"""V-GPS's value function (IQL on stored episodes) and the scorer that ranks a policy's proposals by it."""
