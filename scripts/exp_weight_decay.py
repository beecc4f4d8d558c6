"""The command line of agents.experiments.exp_weight_decay (``--help`` lists the options)."""


from agents.experiments.exp_weight_decay import cli

if __name__ == "__main__":
    cli()
