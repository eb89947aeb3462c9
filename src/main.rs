/// jemalloc, with transparent huge pages (.cargo/config.toml): the
/// adjustment allocates its Jacobians and normal matrices afresh (tens of
/// MB at 24 000 readings), and on a virtual machine each fresh 4 KiB page
/// costs a ~2 µs fault; in 2 MiB pages the `calibrate` stage of 24 000
/// readings takes 7–13 % less (README, "Against Ceres", *Stop 52*).
#[cfg(all(target_os = "linux", not(target_env = "musl")))]
#[global_allocator]
static ALLOCATOR: tikv_jemallocator::Jemalloc = tikv_jemallocator::Jemalloc;

fn main() -> std::process::ExitCode {
    ltcal::run()
}
