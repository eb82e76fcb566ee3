"""The hand-back rule's vocabulary: one name for each of its settings, wherever they appear.

``policy.controller.ControllerConfig`` (the rule itself), the service's settings
(``server.settings.Settings``) and the assisted rollouts' ``lab.assisted.AssistConfig`` use these
names. A module of its own, with no import, so that reading the service's settings loads no torch.
"""

HAND_BACK = ("budgeted", "continuous")  # the values of ``hand_back``
# the values of ``resume``: what the policy sees first after a hand-back. ``restart``: a fresh observation
# history, filled with the current frame; ``history``: the history as the takeover left it, so a policy that
# sees several frames sees the operator's motion (a policy with an observation history of 1 sees the same)
RESUME = ("restart", "history")
HAND_BACK_FIELDS = ("hand_back", "budget", "return_after", "cooldown", "resume")
