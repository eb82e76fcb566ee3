"""Clients of the service's HTTP API: programs that use only its public REST routes, as a user's
program would (``client.operator_bot``: the simulated operator). Nothing here imports the service
(``server``, ``web``, ``service``) or the benchmarks; the benchmarks and the ``hitl`` CLI use these."""
