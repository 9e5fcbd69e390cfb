"""Evaluate on a split: ``python evaluate.py [dataset=v6] [split=test]`` (configs in conf/)."""
from dagr_lite.apps.cli import hydra_command
from dagr_lite.engine.evaluate import evaluate

main = hydra_command("evaluate", evaluate)

if __name__ == "__main__":
    main()
