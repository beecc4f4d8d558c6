"""The command line of agents.experiments.bench_suite (``--help`` lists the options).

    python scripts/bench_suite.py --json docs/results/bench_suite.json --figures docs/figures
    python scripts/bench_suite.py --smoke --json runs/bench_suite_smoke.json   # CI, ~1 min
"""


from agents.experiments.bench_suite import main

if __name__ == "__main__":
    main()
