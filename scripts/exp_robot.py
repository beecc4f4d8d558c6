"""The command line of agents.experiments.exp_robot (``--help`` lists the options)."""


from agents.experiments.exp_robot import cli

if __name__ == "__main__":
    cli()
