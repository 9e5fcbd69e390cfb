"""Train a detector: ``python train.py [dataset=v6] [key=value ...]`` (configs in conf/)."""
from dagr_lite.apps.cli import hydra_command
from dagr_lite.engine.train import train

main = hydra_command("train", train)

if __name__ == "__main__":
    main()
