"""Speed and robustness measurements: maem-bench (``bench``, its standard load ``bench_load``,
``--live`` through the graph in ``live``, ``live_report`` and ``live_runs``), the latency replay
(``latency``) and maem-soak (``soak``: minutes of graph, memory and drops)."""
