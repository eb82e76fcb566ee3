"""The lab: the simulated-operator rollout machinery and the experiments that the benchmarks (``bench``)
and the CLI (``hitl``) use, apart from the product. ``assisted`` runs assisted rollouts with the task's
scripted expert as the operator, ``fields`` keeps what the uncertainty figures plot, ``experts`` measures
the scripted experts, and ``spread_stall`` is the superseded asking signal that committed results
compare with, registered (``signals.registered``) only where a benchmark or experiment asks for
it. Product packages (``storage``, ``sim``, ``policy``, ``server``, ``web``, ``service``, ``client``) never
import it; it imports them.
"""
