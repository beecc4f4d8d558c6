"""The command line of agents.experiments.exp_activations (``--help`` lists the options)."""


from agents.experiments.exp_activations import cli

if __name__ == "__main__":
    cli()
