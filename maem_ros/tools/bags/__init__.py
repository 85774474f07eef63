"""Bag tools: maem-bag (``bag``: info, recover), maem-make-bag (``make_bag``: a bag from frames,
videos or a sim scene) and maem-record-faults (``record_faults``: crash, cut and full-disk runs;
``record_faults_cli``: its command line)."""
