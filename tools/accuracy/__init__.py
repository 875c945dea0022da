"""The parts of tools/bench_accuracy.py, the accuracy benchmark (that file is its command line): splits.py, the
data and the splits of it the benchmark runs; runners.py, the map builds and the localization of every query into
rows; report.py, the rows as tables and statistics. The modules import each other (report and runners use
splits, runners uses report's fmt_row) and nothing else of tools/; bench_accuracy.py puts tools/ on sys.path so
that this package imports as ``accuracy``."""
