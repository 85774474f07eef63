"""maem-eval (``evaluate``: MAEM offline on a scene folder, scored against its ground truth),
where association loses people (``explain``) and its PNG plots (``plots``)."""
