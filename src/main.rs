fn main() -> std::process::ExitCode {
    ltcal::run()
}
