"""maem-eval (``evaluate``: MAEM offline on a scene folder, scored against its ground truth;
``results``: each configuration's metrics, tables and predictions file), where association loses
people (``explain``), its PNG plots (``plots``) and its options (``options``)."""
