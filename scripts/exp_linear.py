"""The command line of agents.experiments.exp_linear (``--help`` lists the options)."""


from agents.experiments.exp_linear import cli

if __name__ == "__main__":
    cli()
