#!/usr/bin/env bash
# Copies the merged paired halves (runs/s41/eval/<arm>/<task>.<seed>.results.json) into docs/results/sw-s42/.
cd /work/main
for arm in sw pb5 gr; do
  for f in runs/s41/eval/$arm/*.[0-9]*[0-9].results.json; do
    [ -f "$f" ] && [[ "$f" != *.s[0-9].results.json ]] || continue
    mkdir -p docs/results/sw-s42/$arm && cp "$f" docs/results/sw-s42/$arm/
  done
done
ls docs/results/sw-s42/*
