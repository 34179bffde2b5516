#!/bin/bash
# Call 2 of 3 (carry .gpuB): Warp's second piece.
cp .gpuB/w1 /tmp/g/ && ls -l /tmp/g
