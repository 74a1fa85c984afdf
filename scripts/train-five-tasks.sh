#!/usr/bin/env bash
# The shipped five-task checkpoint (models/policy/pretrained/five-tasks, see its model card):
# 100 demonstrations per task, models/policy/cpu.toml (about 49 min of training on a 2-core
# machine), evaluation on 50 held-out seeds per task. See scripts/train-tasks.sh.
exec "$(dirname "${BASH_SOURCE[0]}")/train-tasks.sh" five-tasks models/policy/cpu.toml \
  open_drawer push_buttons slide_block close_jar stack_blocks
