"""What one command does, from images to its output: the orchestration that runs descriptors over
data and then matches, decides or evaluates, above the stages it drives (data, descriptors,
matching, decisions, evaluation). The command line parses arguments and calls one of these."""
