fn main() { ltcal::placeholder(); }
