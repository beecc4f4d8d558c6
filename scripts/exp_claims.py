"""The command line of agents.experiments.exp_claims (``--help`` lists the options)."""


from agents.experiments.exp_claims import cli

if __name__ == "__main__":
    cli()
