"""``hitl bench finetune``: fine-tuning on takeover data against full trajectories (``run``) and its
report, table and figure (``report``)."""
