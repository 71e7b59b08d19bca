// Rebuild when a migration is added or changed: `sqlx::migrate!` embeds the migrations/ folder.
fn main() {
    println!("cargo:rerun-if-changed=migrations");
}
