"""SAC trained inside the learned model (agents.model_env.ModelEnv), evaluated in the real env
(agents.experiments.model_env_sac).

    python scripts/model_env_sac.py                        # 6 real episodes, 5000 model steps
"""


from agents.cli import main
from agents.experiments.model_env_sac import Args, run

if __name__ == "__main__":
    main(Args, run, outputs=("json",))
