fn main() {
    println!("himap: under construction");
}
