"""Every ``hitl bench …`` command, the reports, the figures and the screenshots.

Only ``hitl/`` and ``tests/`` import this package; nothing in the product does. Each command lives
in the module of its name, the two large ones in packages:

- ``hitl/`` (``hitl bench hitl``): the human-in-the-loop benchmark on the paper's protocol (``run``),
  its summary (``report``) and its markdown section and figures (``docs``);
- ``finetune/`` (``hitl bench finetune``): fine-tuning on takeover data against full trajectories
  (``run``) and its report (``report``);
- ``hitl_service`` (``hitl bench hitl-service``): the same protocol through the running service;
- ``uncertainty``, ``signals``, ``fleet``: what a robot-step, a signal and a fleet tick cost as served;
- ``api``, ``loop``, ``finetune_load``, ``console``: the service under load;
- ``harness``: what those share (the service in this process, client processes, measurement windows,
  timers); ``report_sections``: the generated sections of a benchmark page (``--report``, ``--section``);
- ``sanity``, ``separation``, ``figures``: ``hitl report sanity``, ``hitl report separation``,
  ``hitl plot uncertainty``; ``screenshots``: ``hitl docs screenshots``.
"""
