"""The command line of agents.experiments.exp_deviations (``--help`` lists the options)."""


from agents.experiments.exp_deviations import cli

if __name__ == "__main__":
    cli()
