"""The application: the commands ``render-and-denoise``, ``denoise`` and ``tradeoff`` (``cli``,
``run``, ``denoise_file``, ``tradeoff``, ``budget``), the one evaluation loop the commands and the
benchmarks share (``evaluation``: render in halves -> denoise -> score), the Pareto and equal-quality
maths (``pareto``) and the reports (``report``, ``tradeoff_report``, ``viewer``). Uses every package
below it; nothing imports it."""
