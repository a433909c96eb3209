<script>
async function refresh(){
  try{
    const r = await fetch(FRAGMENT_URL, {credentials:'same-origin', cache:'no-store'});
    if(r.status === 401){ location.reload(); return; }
    if(r.ok){ document.getElementById('live').innerHTML = await r.text();
              document.getElementById('updated').textContent = new Date().toLocaleTimeString(); }
  }catch(e){ document.getElementById('updated').textContent = 'offline: ' + e; }
}
setInterval(refresh, 2000);
</script>
