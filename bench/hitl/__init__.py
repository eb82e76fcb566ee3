"""``hitl bench hitl``: the human-in-the-loop benchmark on the paper's protocol (``run``), its summary
(``report``) and its markdown section and figures (``docs``)."""
