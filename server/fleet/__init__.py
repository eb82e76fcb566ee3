"""The fleet: simulated or real robots driven by their policies' one control step, helped by operators.

``Fleet`` (``server.fleet.fleet``) puts the parts together and is what the API and the console use, through
``server.port.FleetPort``. Import each part from its module: the package imports nothing. A robot's mode
and counters are ``policy.hitl_state.RobotControl`` (no torch to read them). The parts, from the one that
composes them down to the records they share (no import circle among them, type-only imports included:
``tests/test_layout.py``):

- ``fleet``: builds the robots and composes the parts below; starts and stops the threads; what operators,
  admins and the consoles ask (claims, commands, pauses, resets, views), each left in a robot's inbox;
- ``loop``: the control tick, which alone changes a robot, applying what the API left in its inbox;
- ``lifecycle``: a robot's worker, episodes and takeovers, the transitions the loop makes;
- ``policy_swap`` (which policy version drives a robot), ``recording`` (what is written), ``metrics`` (the
  figures and the operators' clock), ``assistance`` (the queue and its leases);
- ``robot`` (a robot's record and published view), over ``slots`` (a loaded policy version), ``inbox`` and
  ``commands`` (what an API call leaves for the loop's next tick, and how commands compose).
"""
