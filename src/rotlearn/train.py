"""`python -m rotlearn.train ...`: the same as `rotlearn-train`."""

from rotlearn.cli.train import main

if __name__ == "__main__":
    main()
