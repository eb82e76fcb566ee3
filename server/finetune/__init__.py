"""The fine-tuning job: what it is asked and plans (``plan``), the runner that holds the lease and the
job's row (``job``), its seven stages (``stages``, given a ``context.JobContext``), and the nightly
schedule and job process inside ``hitl serve`` (``scheduler``).

Calls run one way: ``job`` -> ``stages`` -> ``context``, ``plan``; ``scheduler`` imports none of them
(it starts ``hitl finetune`` as a process), so ``server.settings`` reads its cron parser without torch.
Import each from its module: the package imports nothing.
"""
