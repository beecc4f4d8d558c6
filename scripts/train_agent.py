"""Train the Algorithm-1 agent (JacProp model learning + iLQR MPC) on the two-link arm
(agents.experiments.train_agent; every AgentConfig field is a flag, see --help).

    python scripts/train_agent.py                       # embedded defaults, mbtsr/TwoLinkArm-v0
    python scripts/train_agent.py --seed 3 --regularization exact --json bench.json
    python scripts/train_agent.py --run-dir runs/x --resume   # continue a killed run exactly
    python scripts/train_agent.py --config runs/x/config.json # run x again, in a new folder
"""


from agents.experiments.train_agent import main

if __name__ == "__main__":
    main()
