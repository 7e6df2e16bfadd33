"""What `sefa bench data` and benchmarks/ measure: ingest and sampling throughput
(`throughput`) and the camera recordings it transcodes from the real Push-T frames
(`pusht_bags`)."""
