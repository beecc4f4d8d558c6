"""The command line of agents.experiments.exp_regime (``--help`` lists the options)."""


from agents.experiments.exp_regime import cli

if __name__ == "__main__":
    cli()
